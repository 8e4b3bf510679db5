"""Two training runs on two cores: one at a time with two threads each, or side by side with one thread each?
And the ResNet's memory format while training: channels-last or NCHW? (`gsmn experiment table2 --parallel`;
docs/training.md, "The ablation programme"; docs/model.md, "Speed").

    python scripts/bench_training_layout.py --data runs/table2/data/expert_dev [--batches 40] [--repeats 3]
    python scripts/bench_training_layout.py --data ... --layouts "side by side" --formats channels-last,nchw

Each trial trains GSMN (batch 1, one episode a batch, the supervised step of `gsmn train supervised`) on the store's
episodes in turn, in fresh processes: "serial" runs two processes one after the other with 2 threads each, "side by
side" runs two at once with 1 thread each; "nchw" trains the ResNet as `gsmn train` does on the CPU (NCHW: its
`memory_format()` in train mode), "channels-last" forces it to channels-last, as inference runs it. Prints the
frames per second of the pair (total frames over wall time) for each trial and the medians; the variants alternate
within one run, so their ratios are measured side by side.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

LAYOUTS = ("serial", "side by side")
FORMATS = ("channels-last", "nchw")


def train(data: str, batches: int, threads: int, memory_format: str) -> None:
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
    if memory_format == "channels-last":  # as the ResNet trained on the CPU before it kept NCHW for training
        model.resnet.memory_format = lambda: torch.channels_last
        model.train()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    frames = 0
    for i in range(batches):
        frames += int(train_step(model, optimizer, [store.read(keys[i % len(keys)])], vocabulary, config, i)["frames"])
    print(json.dumps({"frames": frames}))


def trial(data: str, batches: int, layout: str, memory_format: str) -> float:
    command = [sys.executable, __file__, "--worker", "--data", data, "--batches", str(batches), "--formats",
               memory_format]
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
    parser.add_argument("--layouts", default=",".join(LAYOUTS), help="comma-separated, of: " + ", ".join(LAYOUTS))
    parser.add_argument("--formats", default=FORMATS[0],
                        help="the ResNet's memory format while training, comma-separated, of: " + ", ".join(FORMATS))
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    layouts, formats = args.layouts.split(","), args.formats.split(",")
    if not set(layouts) <= set(LAYOUTS) or not set(formats) <= set(FORMATS):
        parser.error(f"--layouts of {LAYOUTS}, --formats of {FORMATS}")
    if args.worker:
        train(args.data, args.batches, args.threads, formats[0])
        return
    rates: dict[tuple[str, str], list[float]] = {(layout, f): [] for layout in layouts for f in formats}
    for r in range(args.repeats):
        for layout, f in rates:
            rates[layout, f].append(trial(args.data, args.batches, layout, f))
            print(f"trial {r + 1}, {layout}, {f}: {rates[layout, f][-1]:.1f} frames/s (the pair)", flush=True)
    medians = {key: statistics.median(v) for key, v in rates.items()}
    for (layout, f), median in medians.items():
        print(f"median: {layout} ({'2 threads' if layout == 'serial' else '1 thread'} each), {f}: {median:.1f} "
              "frames/s")
    first = next(iter(rates))
    for key in list(rates)[1:]:
        ratios = [a / b for a, b in zip(rates[key], rates[first], strict=True)]
        print(f"{', '.join(key)} / {', '.join(first)} = {medians[key] / medians[first]:.2f} (per trial: "
              f"{', '.join(f'{x:.2f}' for x in ratios)})")


if __name__ == "__main__":
    main()
