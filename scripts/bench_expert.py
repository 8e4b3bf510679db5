"""Benchmark: expert episodes per minute on this machine, with 1 and 2 worker processes, with and without
rendering the camera (evaluation of the expert does not need images; data collection does).

    python scripts/bench_expert.py [--episodes 30] [--repeats 3] [--preset paper]

Each figure is the median over repeats of episodes / wall-clock minutes, over the same test environments.
The 2-worker figure includes starting the worker processes.
"""

from __future__ import annotations

import argparse
import statistics
import time

from gsmn.config import preset
from gsmn.evaluation import evaluate
from gsmn.world.spec import split_env_ids


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--preset", default="paper")
    args = parser.parse_args()
    config = preset(args.preset)
    env_ids = split_env_ids("test", args.episodes)
    print(f"expert ({args.preset} preset), {args.episodes} test episodes, median of {args.repeats} runs")
    print(f"{'render':>7} {'workers':>8} {'episodes/min':>13} {'steps/s':>9}")
    for render in (False, True):
        for workers in (1, 2):
            rates, step_rates = [], []
            for _ in range(args.repeats):
                t = time.perf_counter()
                records = evaluate("oracle", env_ids, config, workers=workers, render=render)
                dt = time.perf_counter() - t
                rates.append(60 * len(records) / dt)
                step_rates.append(sum(r.steps for r in records) / dt)
            rate, step_rate = statistics.median(rates), statistics.median(step_rates)
            print(f"{str(render):>7} {workers:8d} {rate:13.1f} {step_rate:9.1f}")


if __name__ == "__main__":
    main()
