"""How DAggerFM's 4.5 m cut shapes a policy's own rollouts: each checkpoint flies the same train environments as
DAggerFM's beta-0 mixture flies them (the learner acts at every step, the expert only labels), once with the cut
(`dagger.max_deviation`) and once without, and the flights are scored as `gsmn eval` scores them.

    MUJOCO_GL=egl python scripts/cut_rate.py checkpoints/gsmn checkpoints/gs-fpv --episodes 24 --json out.json

The environments are the first N of the train environments the baselines' DAggerFM draws from (train ids from 600
on, `runs/stage28.sh`). A flight the cut ends early ends with a STOP the learner did not choose, on a frame whose
label is the expert's (fly back to the path), so a policy whose rollouts are mostly cut trains on little of what
happens when it stops near its goal. `stop_labels` counts the frames where the expert said STOP (within its
radius of the goal): a flight can have them and still fail, having flown on past the goal (docs/training.md,
"What the baselines' DAggerFM data holds").
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from gsmn.config import RunConfig
from gsmn.model.checkpoint import load_policy
from gsmn.task.rollout import task_for_env
from gsmn.training.collect import MixturePolicy, fly_and_record
from gsmn.world.env import Env
from gsmn.world.spec import split_env_ids


def fly(env: Env, config: RunConfig, learner, env_id: int, max_deviation: float | None) -> dict:
    policy = MixturePolicy(config, learner=learner, beta=0.0, rng=np.random.default_rng(0),
                           max_deviation=max_deviation)
    sample, record = fly_and_record(env, policy, task_for_env(env_id, config), config.task.horizon)
    return {"success": bool(record.success), "cut": policy.cut, "steps": int(len(sample.actions)),
            "stop_labels": int((sample.actions[:, 2] > 0.5).sum())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoints", nargs="+", help="checkpoint folders")
    parser.add_argument("--episodes", type=int, default=24, help="train environments, from id 600 of the split on")
    parser.add_argument("--first", type=int, default=600, help="index into the train split of the first environment")
    parser.add_argument("--json", help="write every flight here")
    args = parser.parse_args()
    torch.set_num_threads(1)
    config = RunConfig()
    env = Env(config)
    ids = [int(i) for i in split_env_ids("train", 3000)[args.first:args.first + args.episodes]]
    cut = config.dagger.max_deviation
    results: dict[str, list[dict]] = {}
    for folder in args.checkpoints:
        learner = load_policy(folder)
        rows = results[folder] = []
        for env_id in ids:
            row = {"env_id": env_id, "cut": fly(env, config, learner, env_id, cut),
                   "uncut": fly(env, config, learner, env_id, None)}
            rows.append(row)
            print(folder, json.dumps(row), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"env_ids": ids, "max_deviation": cut, "results": results}, indent=1))
    print(f"\n| checkpoint | cut at {cut} m: succeeded | cut | with a STOP label | uncut: succeeded | "
          f"cut flights that succeed uncut |")
    print("|---|---|---|---|---|---|")
    for folder, rows in results.items():
        n = len(rows)
        print(f"| {folder} | {sum(r['cut']['success'] for r in rows)} of {n} | {sum(r['cut']['cut'] for r in rows)} | "
              f"{sum(r['cut']['stop_labels'] > 0 for r in rows)} | {sum(r['uncut']['success'] for r in rows)} of {n} | "
              f"{sum(r['cut']['cut'] and r['uncut']['success'] for r in rows)} |")


if __name__ == "__main__":
    main()
