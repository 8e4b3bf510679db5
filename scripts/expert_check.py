"""Fly the expert (carrot planner on the demonstration path) in the simulator and report the paper's metrics.

A sanity check of the task pieces together (paper: Evaluation Metric, the "Oracle (Expert)" row of the test
table), not a test. Each episode runs until the expert says STOP or the horizon is reached; the final
position is scored either way.

    python scripts/expert_check.py --n 60                  # first 60 test environments
    python scripts/expert_check.py --n 60 --horizon 150 -v  # longer episodes, one line per episode
"""

from __future__ import annotations

import argparse
import dataclasses
import time

from gsmn.config import ExpertConfig, TaskConfig, preset
from gsmn.task.demo import DemoPathError, demonstration_path, path_length
from gsmn.task.expert import Expert
from gsmn.task.instructions import instruction_for_env
from gsmn.task.metrics import EpisodeOutcome, Summary, goal_distance, success, summarize
from gsmn.world.env import Action, Env
from gsmn.world.spec import split_env_ids, world_for_env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=60, help="number of environments")
    parser.add_argument("--split", default="test", help="train, test or dev")
    parser.add_argument("--horizon", type=int, default=TaskConfig().horizon, help="steps per episode")
    parser.add_argument("--preset", default="tiny", help="config preset (rendering cost only)")
    parser.add_argument("-v", "--verbose", action="store_true", help="one line per episode")
    args = parser.parse_args()

    config = preset(args.preset)
    task = dataclasses.replace(TaskConfig(), horizon=args.horizon)
    expert_config = ExpertConfig()
    outcomes: list[EpisodeOutcome] = []
    rejected, timeouts, t0 = [], 0, time.time()
    with Env(config) as env:
        for env_id in split_env_ids(args.split, args.n):
            world = world_for_env(env_id, config.world)
            instruction = instruction_for_env(world, task)
            try:
                path = demonstration_path(world, instruction.goal, expert_config)
            except DemoPathError as e:
                rejected.append(env_id)
                print(f"rejected: {e}")
                continue
            expert = Expert(path, expert_config, config.drone)
            obs = env.reset(env_id, instruction.text, world)
            stopped = False
            for _ in range(task.horizon):
                action = expert.act(obs.pose.position, obs.pose.yaw)
                if action.stop:
                    stopped = True
                    break
                obs = env.step(Action(action.forward_velocity, action.yaw_rate))
            timeouts += not stopped
            final = obs.pose.position[:2]
            outcome = EpisodeOutcome.of(world, instruction, final)
            outcomes.append(outcome)
            if args.verbose:
                ok = success(final, (outcome.landmark_x, outcome.landmark_y), world.start_position,
                             instruction.side, task.success_radius)
                print(f"env {env_id:5d} {instruction.side:5s} path {path_length(path):5.1f} m  steps {obs.step:3d} "
                      f"{'STOP' if stopped else 'time'}  dist {goal_distance(final, instruction.goal):5.2f} m  "
                      f"{'ok' if ok else 'FAIL'}  {instruction.text}")
    summary = summarize(outcomes, task.success_radius)
    print(f"{args.split}: {len(outcomes)} episodes flown, {len(rejected)} demonstrations rejected {rejected}, "
          f"{timeouts} reached the {task.horizon}-step horizon without STOP ({time.time() - t0:.0f} s)")
    _print("all", summary)
    if summary.pruned is not None:
        _print("pruned", summary.pruned)


def _print(name: str, s: Summary) -> None:
    print(f"{name:6s} n={s.count:4d}  success {s.success:5.1f} %  landmark success {s.landmark_success:5.1f} %  "
          f"distance mean {s.mean_distance:.2f} m  median {s.median_distance:.2f} m")


if __name__ == "__main__":
    main()
