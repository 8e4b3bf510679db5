"""Two training runs on two cores: one at a time with two threads each, or side by side with one thread each?
(`gsmn experiment table2 --parallel`; docs/training.md, "The ablation programme").

    python scripts/bench_training_layout.py --data runs/table2/data/expert_dev [--batches 40] [--repeats 3]

Each trial trains GSMN (batch 1, one episode a batch, the supervised step of `gsmn train supervised`) on the store's
episodes in turn, in fresh processes: "serial" runs two processes one after the other with 2 threads each, "side by
side" runs two at once with 1 thread each. Prints the frames per second of the pair (total frames over wall time)
for each trial and the medians; the two layouts alternate within one run, so their ratio is measured side by side.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time


def train(data: str, batches: int, threads: int) -> None:
    import torch

    from gsmn.config import RunConfig
    from gsmn.model.models import build_model
    from gsmn.model.runtime import keep_freed_memory
    from gsmn.model.vocabulary import Vocabulary
    from gsmn.training.store import EpisodeStore
    from gsmn.training.supervised import train_step

    keep_freed_memory()
    torch.set_num_threads(threads)
    config, store = RunConfig(), EpisodeStore(data)
    keys = store.keys()
    vocabulary = Vocabulary.default()
    torch.manual_seed(0)
    model = build_model("gsmn", config, vocabulary)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    frames = 0
    for i in range(batches):
        frames += int(train_step(model, optimizer, [store.read(keys[i % len(keys)])], vocabulary, config, i)["frames"])
    print(json.dumps({"frames": frames}))


def trial(data: str, batches: int, layout: str) -> float:
    command = [sys.executable, __file__, "--worker", "--data", data, "--batches", str(batches)]
    t0, frames = time.perf_counter(), 0
    if layout == "serial":
        for _ in range(2):
            out = subprocess.run([*command, "--threads", "2"], capture_output=True, text=True, check=True).stdout
            frames += json.loads(out.splitlines()[-1])["frames"]
    else:
        procs = [subprocess.Popen([*command, "--threads", "1"], stdout=subprocess.PIPE, text=True) for _ in range(2)]
        for p in procs:
            out, _ = p.communicate()
            frames += json.loads(out.splitlines()[-1])["frames"]
    return frames / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="an episode store (gsmn collect)")
    parser.add_argument("--batches", type=int, default=40, help="batches each process trains (default 40)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        train(args.data, args.batches, args.threads)
        return
    rates: dict[str, list[float]] = {"serial": [], "side by side": []}
    for r in range(args.repeats):
        for layout in rates:
            rates[layout].append(trial(args.data, args.batches, layout))
            print(f"trial {r + 1}, {layout}: {rates[layout][-1]:.1f} frames/s (the pair)", flush=True)
    serial, side = statistics.median(rates["serial"]), statistics.median(rates["side by side"])
    print(f"median: serial (2 threads each) {serial:.1f} frames/s, side by side (1 thread each) {side:.1f} frames/s; "
          f"side by side / serial = {side / serial:.2f}")


if __name__ == "__main__":
    main()
