"""How fast training can be fed: episodes read (and mirrored) from a store, in turn or on `train.prefetch` threads.

On a lent GPU the data read held training at about 800-1100 frames/s against the model's 2671 (GSMN) and
4200-4400 (the baselines) at batch 1 (docs/model.md): reading an episode and mirroring it cost about 0.4 ms a
frame each on one core. This prints the frames/s at which `gsmn.training.supervised.read_batches` hands over
batches (batch 1, the epoch's order) for each prefetch setting, medians of several passes:

- alone: nothing consumes but the loop, so this is the reading's own ceiling;
- beside a consumer that spends 1/CONSUMER_FPS s a frame on each batch, either waiting without the GIL
  (`time.sleep`, as a process waiting on the GPU does) or spinning in Python with it (as one launching small
  kernels one by one partly does); a real training process lies in between. This shows how much of the reading
  the threads hide.

    python scripts/bench_reading.py --data data/expert_train [--episodes 120] [--mirror 0.5]
                                    [--prefetch 0 1 2 4] [--consumer-fps 2671] [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

from gsmn.training.store import EpisodeStore
from gsmn.training.supervised import epoch_batches, read_batches


def spin(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def one_pass(store: EpisodeStore, keys: list[str], mirror: float, prefetch: int, consumer_fps: float,
             epoch: int, wait=time.sleep) -> float:
    batches = epoch_batches(keys, 1, 0, epoch)
    frames, t0 = 0, time.perf_counter()
    for samples in read_batches(store, batches, 0, mirror, 0, epoch, prefetch):
        n = sum(len(s.images) for s in samples)
        frames += n
        if consumer_fps:
            wait(n / consumer_fps)
    return frames / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True)
    parser.add_argument("--episodes", type=int, default=120)
    parser.add_argument("--mirror", type=float, default=0.5)
    parser.add_argument("--prefetch", type=int, nargs="+", default=[0, 1, 2, 4])
    parser.add_argument("--consumer-fps", type=float, default=2671.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    store = EpisodeStore(args.data)
    keys = store.keys()[:args.episodes]
    if not keys:
        raise SystemExit(f"no episodes in {args.data}")
    one_pass(store, keys[:8], args.mirror, 0, 0, 99)  # warm the imports and the page cache's directory
    print(f"{len(keys)} episodes of {args.data}, batch 1, mirror {args.mirror}; frames/s, median of {args.repeats}")
    fps = args.consumer_fps
    for consumer, wait, label in ((0.0, time.sleep, "alone"),
                                  (fps, time.sleep, f"beside a {fps:.0f} f/s waiting consumer"),
                                  (fps, spin, f"beside a {fps:.0f} f/s spinning consumer")):
        for prefetch in args.prefetch:
            runs = [one_pass(store, keys, args.mirror, prefetch, consumer, r, wait) for r in range(args.repeats)]
            print(f"{label:>42}  prefetch {prefetch}: {statistics.median(runs):7.0f}"
                  f"  (runs {', '.join(f'{r:.0f}' for r in runs)})")


if __name__ == "__main__":
    main()
