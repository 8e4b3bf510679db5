"""Episodes per second of evaluation, expert collection and DAggerFM rollouts, side by side in one run: with each
shadow look, and optionally the same with an earlier version of the code (a git worktree) as "before".

    .venv/bin/python scripts/bench_throughput.py [--episodes 6] [--repeats 3] [--workers 2] [--before TREE]

    git worktree add /tmp/before 1e2fee2^    # the code before baked shadows and the float controller
    .venv/bin/python scripts/bench_throughput.py --before /tmp/before

All three are bound by rendering (docs/world.md), so they gain what the camera's look gains. Each column runs in a
process of its own (its tree first on PYTHONPATH), the columns in rotating order per repeat so drifting load falls on
all alike: `evaluate` of the shipped GSMN on the first test environments (`--workers` processes of one thread each),
`collect_expert` of the same environments into a fresh store (`--workers` processes), and DAggerFM's rollout worker
(`gsmn.training.dagger._rollout_one`, in that process, one thread) flying the shipped GSMN mixed with the expert at
beta 0.5 and writing each rollout. Worker start-up is included in the first two, as a job pays it. Medians of the
repeats, each column's ratio to the first, and the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
WHAT = ("evaluation", "collection", "DAggerFM rollouts")


def _rate(n: int, fn) -> float:
    t = time.perf_counter()
    fn()
    return n / (time.perf_counter() - t)


def measure(look: str, episodes: int, workers: int) -> dict[str, float]:
    """One column's figures, in this process: the code on sys.path, the look `look` (MuJoCo's where the code has no
    choice of look)."""
    import dataclasses

    import torch

    import gsmn  # noqa: F401  (sets MUJOCO_GL before mujoco loads)
    from gsmn.config import CameraConfig, preset
    from gsmn.evaluation import checkpoint_path, evaluate
    from gsmn.training import dagger
    from gsmn.training.collect import collect_expert
    from gsmn.training.store import EpisodeStore
    from gsmn.world.spec import split_env_ids

    config = preset("paper")
    if "shadow_method" in {f.name for f in dataclasses.fields(CameraConfig)}:
        config = dataclasses.replace(config, camera=dataclasses.replace(config.camera, shadow_method=look))
    elif look != "mujoco":
        raise SystemExit(f"this code has no look {look!r}")
    ids = split_env_ids("test", episodes)
    with tempfile.TemporaryDirectory() as scratch:
        out = {"evaluation": _rate(len(ids), lambda: evaluate("gsmn", ids, config, workers=workers)),
               "collection": _rate(len(ids), lambda: collect_expert(EpisodeStore(Path(scratch) / "expert"), ids,
                                                                   config, workers=workers))}
        torch.set_num_threads(1)
        dagger._init_worker(config, str(Path(scratch) / "dagger"), str(checkpoint_path("gsmn")))
        try:
            jobs = [(f"r{k}", env_id, 1, 0.5, k) for k, env_id in enumerate(ids)]
            out["DAggerFM rollouts"] = _rate(len(ids), lambda: [dagger._rollout_one(job) for job in jobs])
        finally:
            dagger._worker.pop("env").close()
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", type=int, default=6, help="test environments per measurement")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--workers", type=int, default=2, help="worker processes for evaluation and collection")
    p.add_argument("--before", default=None, metavar="TREE", help="a checkout of earlier code: a 'before' column")
    p.add_argument("--one", default=None, metavar="LOOK", help=argparse.SUPPRESS)  # a column's process
    a = p.parse_args()
    if a.one:
        print(json.dumps(measure(a.one, a.episodes, a.workers)))
        return
    columns = ([("before, MuJoCo's shadow passes", Path(a.before).resolve(), "mujoco")] if a.before else []) + [
        ("MuJoCo's shadow passes", REPO, "mujoco"), ("baked shadows", REPO, "baked")]
    rates: dict[str, dict[str, list[float]]] = {name: {w: [] for w in WHAT} for name, _, _ in columns}
    for r in range(a.repeats):
        for name, tree, look in columns[r % len(columns):] + columns[: r % len(columns)]:
            env = {**os.environ, "PYTHONPATH": str(tree)}
            out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--one", look, "--episodes",
                                  str(a.episodes), "--workers", str(a.workers)], cwd=tree, env=env, check=True,
                                 capture_output=True, text=True).stdout
            figures = json.loads(out.strip().splitlines()[-1])
            for w in WHAT:
                rates[name][w].append(figures[w])
            print(f"repeat {r + 1}, {name}: " + ", ".join(f"{w} {figures[w]:.3f}/s" for w in WHAT), flush=True)
    print(f"\n{a.episodes} test environments, {a.workers} workers (DAggerFM rollouts: 1), {a.repeats} repeats, "
          f"load average {os.getloadavg()[0]:.2f}; episodes per second, medians (ratio to the first column)")
    print("| | " + " | ".join(name for name, _, _ in columns) + " |")
    print("|---|" + "---|" * len(columns))
    for w in WHAT:
        first = statistics.median(rates[columns[0][0]][w])
        cells = [f"{(m := statistics.median(rates[name][w])):.3f} ({m / first:.2f}x)" for name, _, _ in columns]
        print(f"| {w} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
