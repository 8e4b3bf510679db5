"""The expert and the trivial baselines as policies (paper: Systems; Table 1's lower rows).

- `oracle`: the carrot expert following the demonstration path.
- `avg-forward`: the average action for the average number of steps, both measured from expert rollouts
  on the train split (`fit_avg_forward`, stored as a small JSON "checkpoint").
- `random-point`: fly to a uniformly random point of the field and stop there.
- `random-landmark`: fly to the instructed side of a uniformly random landmark of the world. The original
  mapped front/back to front by mistake; here every side is its own.

The two "fly to" baselines plan a path to their target with the same point-mass planner as the
demonstrations (so they avoid landmarks like the expert) and follow it with the same carrot planner.
Their randomness comes from SeedSequence([seed, env_id, 2]), so an evaluation is repeatable.
"""

from __future__ import annotations

import json
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from gsmn.config import RunConfig
from gsmn.task.demo import DemoPathError, demonstration_path, resample
from gsmn.task.expert import Expert
from gsmn.task.instructions import goal_position
from gsmn.task.rollout import EpisodeRecord, PolicyAction, Task
from gsmn.world.env import Observation

TRIVIAL_SYSTEMS = ("oracle", "avg-forward", "random-point", "random-landmark")


class ExpertPolicy:
    """The carrot planner on the task's demonstration path: the paper's Oracle."""

    name = "oracle"
    needs_images = False

    def __init__(self, config: RunConfig):
        self.config = config
        self.expert: Expert | None = None

    def reset(self, task: Task) -> None:
        self.expert = Expert(task.path, self.config.expert, self.config.drone)

    def act(self, obs: Observation) -> PolicyAction:
        a = self.expert.act(obs.pose.position[:2], obs.pose.yaw)
        return PolicyAction(a.forward_velocity, a.yaw_rate, a.stop)


class _GoToPolicy(ExpertPolicy, ABC):
    """Follows a planned path to a target chosen at reset by `target`."""

    def reset(self, task: Task) -> None:
        rng = np.random.default_rng(np.random.SeedSequence([self.config.task.seed, task.world.env_id, 2]))
        goal = self.target(task, rng)
        try:
            path = demonstration_path(task.world, goal, self.config.expert)
        except DemoPathError:  # a target boxed in behind a landmark: fly straight
            path = resample(np.stack([task.world.start_position, goal]), self.config.expert.waypoint_spacing)
        self.expert = Expert(path, self.config.expert, self.config.drone)

    @abstractmethod
    def target(self, task: Task, rng: np.random.Generator) -> np.ndarray:
        """Where to fly, drawn with `rng`."""


class RandomPointPolicy(_GoToPolicy):
    name = "random-point"

    def target(self, task: Task, rng: np.random.Generator) -> np.ndarray:
        return rng.uniform(0.0, task.world.field_size, size=2)


class RandomLandmarkPolicy(_GoToPolicy):
    name = "random-landmark"

    def target(self, task: Task, rng: np.random.Generator) -> np.ndarray:
        index = int(rng.integers(len(task.world.landmarks)))
        return goal_position(task.world, index, task.instruction.side)


@dataclass(frozen=True)
class AverageAction:
    """The avg-forward baseline's parameters, measured from expert episodes."""

    forward_velocity: float  # m/s, mean over every expert step
    yaw_rate: float  # rad/s, mean over every expert step
    steps: int  # mean episode length, rounded
    episodes: int  # how many expert episodes they were measured on

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"system": "avg-forward", **asdict(self)}, indent=1) + "\n")

    @classmethod
    def load(cls, path: Path) -> AverageAction:
        if not Path(path).is_file():
            raise FileNotFoundError(f"no avg-forward parameters at {path}; make them with `gsmn fit-avg-forward`")
        d = json.loads(Path(path).read_text())
        if d.get("system") != "avg-forward":
            raise ValueError(f"{path} is not an avg-forward parameter file")
        return cls(float(d["forward_velocity"]), float(d["yaw_rate"]), int(d["steps"]), int(d["episodes"]))


def fit_avg_forward(records: list[EpisodeRecord]) -> AverageAction:
    """Average action over all steps flown, and average number of steps, of expert episodes."""
    flown = [a for r in records for a in r.actions if not a[2]]
    v = float(np.mean([a[0] for a in flown]))
    w = float(np.mean([a[1] for a in flown]))
    return AverageAction(v, w, int(round(np.mean([r.steps for r in records]))), len(records))


class AvgForwardPolicy:
    name = "avg-forward"
    needs_images = False

    def __init__(self, average: AverageAction):
        self.average = average

    def reset(self, task: Task) -> None:
        pass

    def act(self, obs: Observation) -> PolicyAction:
        a = self.average
        return PolicyAction(a.forward_velocity, a.yaw_rate, stop=obs.step >= a.steps)
