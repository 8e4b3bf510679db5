"""The residual blocks' 3x3 AvgPool skip while training: PyTorch's avg_pool2d, or the depthwise convolution with
weights 1/9 that `gsmn.model.blocks.AvgPool3x3` uses where autograd tracks it? (docs/model.md, "Speed").

    python scripts/bench_skip_pool.py --data runs/table2/data/expert_dev [--episodes 6] [--repeats 5] [--threads 1]

Trains GSMN (the supervised step of `gsmn train supervised`, one episode a batch) on the store's first episodes,
the two variants alternating within one process, and prints each trial's frames per second, the medians and the
ratio (per trial too), so the ratio is measured side by side.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
import torch.nn as nn

from gsmn.config import RunConfig
from gsmn.model.blocks import AvgPool3x3, ResidualBlock
from gsmn.model.models import build_model
from gsmn.model.runtime import keep_freed_memory
from gsmn.model.vocabulary import Vocabulary
from gsmn.training.store import EpisodeStore
from gsmn.training.supervised import train_step

VARIANTS = ("avg_pool2d", "depthwise conv")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="an episode store (gsmn collect)")
    parser.add_argument("--episodes", type=int, default=6, help="episodes (batches) a trial trains (default 6)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1, as the programme's runs)")
    args = parser.parse_args()
    keep_freed_memory()
    torch.set_num_threads(args.threads)
    config, store, vocabulary = RunConfig(), EpisodeStore(args.data), Vocabulary.default()
    episodes = [store.read(key) for key in store.keys()[: args.episodes]]
    torch.manual_seed(0)
    model = build_model("gsmn", config, vocabulary)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    blocks = [b for b in model.modules() if isinstance(b, ResidualBlock) and isinstance(b.skip, AvgPool3x3)]

    def use(variant: str) -> None:
        for block in blocks:
            stride = block.skip.stride
            block.skip = AvgPool3x3(stride) if variant == VARIANTS[1] else nn.AvgPool2d(3, stride=stride, padding=1)

    for i, episode in enumerate(episodes[:2]):  # warm-up
        train_step(model, optimizer, [episode], vocabulary, config, i)
    rates: dict[str, list[float]] = {v: [] for v in VARIANTS}
    for r in range(args.repeats):
        for variant in VARIANTS:
            use(variant)
            frames, t0 = 0, time.perf_counter()
            for i, episode in enumerate(episodes):
                frames += int(train_step(model, optimizer, [episode], vocabulary, config, i)["frames"])
            rates[variant].append(frames / (time.perf_counter() - t0))
            print(f"trial {r + 1}, {variant}: {rates[variant][-1]:.1f} frames/s", flush=True)
    medians = {v: statistics.median(x) for v, x in rates.items()}
    for variant, median in medians.items():
        print(f"median: {variant}: {median:.1f} frames/s")
    ratios = [a / b for a, b in zip(rates[VARIANTS[1]], rates[VARIANTS[0]], strict=True)]
    print(f"{VARIANTS[1]} / {VARIANTS[0]} = {medians[VARIANTS[1]] / medians[VARIANTS[0]]:.2f} (per trial: "
          f"{', '.join(f'{x:.2f}' for x in ratios)})")


if __name__ == "__main__":
    main()
