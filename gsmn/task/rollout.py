"""Episodes: the task of an environment, the policy interface, and the one rollout function.

`rollout(env, policy, task)` runs any policy (the expert, a learned model, a baseline, a DAgger mixture)
for up to the horizon and returns a typed `EpisodeRecord`; evaluation, data collection and the live
dashboard all use it, the dashboard through the `on_step` callback. A policy's STOP ends the episode
where the drone is (paper: Task, "the agent outputs the action STOP").
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import asdict, dataclass
from typing import Protocol

import numpy as np

from gsmn.config import RunConfig
from gsmn.task.demo import DemoPathError, demonstration_path, resample
from gsmn.task.instructions import Instruction, rng_for_instruction, sample_instruction
from gsmn.task.metrics import goal_distance, landmark_success, success
from gsmn.task.understand import parse_instruction
from gsmn.world.env import Action, Env, Observation
from gsmn.world.spec import WorldSpec, world_for_env


@dataclass(frozen=True)
class Task:
    """An episode to fly: a world, an instruction, and the demonstration path to its goal."""

    world: WorldSpec
    instruction: Instruction
    path: np.ndarray  # (N, 2) demonstration waypoints


def task_for_env(env_id: int, config: RunConfig) -> Task:
    """The task of an environment id, deterministic. Should the sampled instruction's demonstration path
    be rejected (4 in 5000 environments), the next instruction from the same stream is taken."""
    world = world_for_env(env_id, config.world)
    rng = rng_for_instruction(env_id, config.task.seed)
    for _ in range(100):
        instruction = sample_instruction(world, rng, config.task)
        try:
            return Task(world, instruction, demonstration_path(world, instruction.goal, config.expert))
        except DemoPathError:
            continue
    raise DemoPathError(f"no demonstration path for any instruction of environment {env_id}")


def straight_task(world: WorldSpec, instruction: Instruction, spacing: float) -> Task:
    """The instruction with a straight line from the start to its goal as the demonstration path."""
    return Task(world, instruction, resample(np.stack([world.start_position, instruction.goal]), spacing))


def task_for_text(world: WorldSpec, text: str, config: RunConfig, need_path: bool = True) -> Task:
    """The task typed text asks for in `world`: its instruction (`gsmn.task.understand`; InstructionError, readable by
    a user, where it gives none) and the demonstration path to its goal. Where the planner finds no path: a
    DemoPathError with `need_path` (the expert follows the path), else a straight line to the goal (a model flies
    without it; the path is only drawn and scored against)."""
    instruction = parse_instruction(text, world)
    try:
        return Task(world, instruction, demonstration_path(world, instruction.goal, config.expert))
    except DemoPathError:
        if need_path:
            raise
        return straight_task(world, instruction, config.expert.waypoint_spacing)


@dataclass(frozen=True)
class PolicyAction:
    forward_velocity: float  # m/s
    yaw_rate: float  # rad/s, positive turns left
    stop: bool
    stop_probability: float | None = None  # a learned policy's P(stop), on which `stop` was decided
    # a test-time ensemble's members' own P(stop), in its member order (`gsmn.model.policy.Ensemble`), whose mean
    # is `stop_probability`; None for a single model
    member_stop_probabilities: tuple[float, ...] | None = None


class Policy(Protocol):
    name: str
    needs_images: bool  # False lets the environment skip rendering

    def reset(self, task: Task) -> None: ...

    def act(self, obs: Observation) -> PolicyAction: ...


@dataclass(frozen=True)
class EpisodeRecord:
    """One finished episode. Carries the fields `gsmn.task.metrics.summarize` reads."""

    system: str
    env_id: int
    instruction: str
    landmark_index: int
    noun_phrase: str
    side: str
    ambiguous: bool
    goal_x: float
    goal_y: float
    landmark_x: float
    landmark_y: float
    start_x: float
    start_y: float
    final_x: float
    final_y: float
    steps: int  # actions flown before STOP or the horizon
    stopped: bool  # the policy said STOP (else the horizon ended the episode)
    success: bool
    landmark_success: bool
    goal_distance: float
    trajectory: tuple[tuple[float, float, float, float], ...]  # (x, y, z, yaw) at every observation
    actions: tuple[tuple[float, float, bool], ...]  # (v m/s, omega rad/s, stop) at every observation
    # the P(stop) each step was decided on (learned policies; None for the expert, the heuristic baselines, files
    # written before 2026-11-27)
    stop_probabilities: tuple[float, ...] | None = None
    # an ensemble's members' P(stop) at every step (`PolicyAction.member_stop_probabilities`); None otherwise and in
    # files written before 2026-11-28
    member_stop_probabilities: tuple[tuple[float, ...], ...] | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> EpisodeRecord:
        d = dict(d)
        d["trajectory"] = tuple(tuple(p) for p in d["trajectory"])
        d["actions"] = tuple(tuple(a) for a in d["actions"])
        if d.get("stop_probabilities") is not None:
            d["stop_probabilities"] = tuple(d["stop_probabilities"])
        if d.get("member_stop_probabilities") is not None:
            d["member_stop_probabilities"] = tuple(tuple(p) for p in d["member_stop_probabilities"])
        return cls(**d)


OnStep = Callable[[Observation, PolicyAction], None]


@dataclass(frozen=True)
class RolloutStart:
    """Where a rollout that does not begin at the start corner begins (a fork, `gsmn.task.fork`): the environment
    and the policy already stand at observation `obs` (step t), and steps 0..t-1 were flown as these say."""

    obs: Observation
    trajectory: tuple[tuple[float, float, float, float], ...]  # steps 0..t-1, as EpisodeRecord's
    actions: tuple[tuple[float, float, bool], ...]
    stop_probabilities: tuple[float | None, ...]
    member_stop_probabilities: tuple[tuple[float, ...] | None, ...]


def rollout(env: Env, policy: Policy, task: Task, horizon: int, on_step: OnStep | None = None,
            success_radius: float = 6.0, start: RolloutStart | None = None) -> EpisodeRecord:
    """Fly `policy` on `task` until it says STOP or `horizon` actions have been flown; from the start corner, or
    on from `start` (the caller has put `env` and `policy` there)."""
    flight = rollout_steps(env, policy, task, horizon, on_step, success_radius, start)
    while True:
        try:
            next(flight)
        except StopIteration as done:
            return done.value


def rollout_steps(env: Env, policy: Policy, task: Task, horizon: int, on_step: OnStep | None = None,
                  success_radius: float = 6.0, start: RolloutStart | None = None
                  ) -> Generator[int, None, EpisodeRecord]:
    """`rollout` one step at a time: a generator that yields the step t just decided (after `on_step`), with the
    environment still at observation t, before flying its action; it returns the EpisodeRecord. Several episodes
    of one world can share one `Env` this way, the caller saving and restoring its state (`Env.get_state`)
    around each `next` (the dashboard's comparisons)."""
    world, instruction = task.world, task.instruction
    trajectory: list = []
    actions: list = []
    stop_probabilities: list = []
    members: list = []
    stopped = False
    if start is None:
        obs = env.reset(world.env_id, instruction.text, world)
        policy.reset(task)
    else:
        obs = start.obs
        trajectory, actions = list(start.trajectory), list(start.actions)
        stop_probabilities, members = list(start.stop_probabilities), list(start.member_stop_probabilities)
    while True:
        action = policy.act(obs)
        p = obs.pose.position
        trajectory.append((float(p[0]), float(p[1]), float(p[2]), float(obs.pose.yaw)))
        actions.append((float(action.forward_velocity), float(action.yaw_rate), bool(action.stop)))
        stop_probabilities.append(action.stop_probability)
        members.append(action.member_stop_probabilities)
        if on_step is not None:
            on_step(obs, action)
        if action.stop:
            stopped = True
            break
        if obs.step >= horizon:
            break
        yield obs.step
        obs = env.step(Action(action.forward_velocity, action.yaw_rate))
    final = obs.pose.position[:2]
    landmark = world.landmarks[instruction.landmark_index]
    return EpisodeRecord(
        system=policy.name, env_id=world.env_id, instruction=instruction.text,
        landmark_index=instruction.landmark_index, noun_phrase=instruction.noun_phrase, side=instruction.side,
        ambiguous=instruction.ambiguous, goal_x=instruction.goal_x, goal_y=instruction.goal_y,
        landmark_x=landmark.x, landmark_y=landmark.y, start_x=world.start_x, start_y=world.start_y,
        final_x=float(final[0]), final_y=float(final[1]), steps=obs.step, stopped=stopped,
        success=success(final, landmark.position, world.start_position, instruction.side, success_radius),
        landmark_success=landmark_success(final, landmark.position, success_radius),
        goal_distance=goal_distance(final, instruction.goal), trajectory=tuple(trajectory), actions=tuple(actions),
        stop_probabilities=None if None in stop_probabilities else tuple(map(float, stop_probabilities)),
        member_stop_probabilities=None if None in members else tuple(tuple(map(float, m)) for m in members))
