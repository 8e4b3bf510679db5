"""Episodes per second of evaluation, expert collection and DAggerFM rollouts with each shadow look, side by side.

    .venv/bin/python scripts/bench_throughput.py [--episodes 6] [--repeats 3] [--workers 2]

All three are bound by rendering (docs/world.md), so they gain what the camera's look gains. Per repeat, the two
looks in alternating order (drifting load falls on both alike): `evaluate` of the shipped GSMN on the first test
environments (`--workers` processes of one thread each), `collect_expert` of the same environments into a fresh
store (`--workers` processes), and DAggerFM's rollout worker (`gsmn.training.dagger._rollout_one`, in this process,
one thread) flying the shipped GSMN mixed with the expert at beta 0.5 and writing each rollout. Worker start-up is
included in the first two, as a job pays it. Medians of the repeats, the ratio baked / MuJoCo's, and the load
average beside them.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import tempfile
import time
from pathlib import Path

import torch

import gsmn  # noqa: F401  (sets MUJOCO_GL before mujoco loads)
from gsmn.config import preset
from gsmn.evaluation import checkpoint_path, evaluate
from gsmn.training import dagger
from gsmn.training.collect import collect_expert
from gsmn.training.store import EpisodeStore
from gsmn.world.spec import split_env_ids

LOOKS = ("mujoco", "baked")


def _config(look: str):
    config = preset("paper")
    return dataclasses.replace(config, camera=dataclasses.replace(config.camera, shadow_method=look))


def _rate(n: int, fn) -> float:
    t = time.perf_counter()
    fn()
    return n / (time.perf_counter() - t)


def run_once(look: str, ids: list[int], workers: int, scratch: Path) -> dict[str, float]:
    config = _config(look)
    out = {"evaluation": _rate(len(ids), lambda: evaluate("gsmn", ids, config, workers=workers)),
           "collection": _rate(len(ids), lambda: collect_expert(EpisodeStore(scratch / f"expert_{look}"), ids,
                                                               config, workers=workers))}
    torch.set_num_threads(1)
    dagger._init_worker(config, str(scratch / f"dagger_{look}"), str(checkpoint_path("gsmn")))
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
    a = p.parse_args()
    ids = split_env_ids("test", a.episodes)
    rates: dict[str, dict[str, list[float]]] = {look: {} for look in LOOKS}
    for r in range(a.repeats):
        for look in LOOKS if r % 2 == 0 else LOOKS[::-1]:
            with tempfile.TemporaryDirectory() as scratch:
                for what, value in run_once(look, ids, a.workers, Path(scratch)).items():
                    rates[look].setdefault(what, []).append(value)
            print(f"repeat {r + 1} {look}: " + ", ".join(f"{w} {v[-1]:.3f}/s" for w, v in rates[look].items()),
                  flush=True)
    print(f"\n{a.episodes} test environments, {a.workers} workers (DAggerFM rollouts: 1), {a.repeats} repeats, "
          f"load average {os.getloadavg()[0]:.2f}; episodes per second, medians")
    print(f"| {'':20} | MuJoCo's shadow passes | baked shadows | baked / MuJoCo's |")
    print("|---|---|---|---|")
    for what in rates["mujoco"]:
        m, b = statistics.median(rates["mujoco"][what]), statistics.median(rates["baked"][what])
        print(f"| {what:20} | {m:.3f} | {b:.3f} | {b / m:.2f}x |")


if __name__ == "__main__":
    main()
