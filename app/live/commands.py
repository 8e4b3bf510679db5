"""The runner's vocabulary: the commands the page and the API post, what comes back, the errors (each with the
HTTP status the API answers with), and what the runner tells its listeners.

A command carries a `Future`; the runner answers it with a result or a `RunnerError` whose message is meant for
users.
"""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.live.recording import Episode, StepRecord
from gsmn.task.instructions import Instruction
from gsmn.task.rollout import Task
from gsmn.world.spec import WorldSpec

POLICIES = ("model", "mirror", "expert")  # "mirror": the model as a test-time mirror ensemble
MAX_ENV_ID = 2**31 - 1
MAX_QUEUED = 8  # episodes waiting to fly behind the live one; more are refused (each flies for up to minutes)


# -- errors the API turns into 4xx answers --------------------------------------------------------------------
class RunnerError(Exception):
    """A command cannot be done; the message is meant for users. `status` is the HTTP status it maps to."""

    status = 422


class NotFound(RunnerError):
    status = 404


class Conflict(RunnerError):
    status = 409


class Forbidden(RunnerError):
    status = 403


class TooLarge(RunnerError):
    status = 413


# -- commands -------------------------------------------------------------------------------------------------
@dataclass
class Command:
    future: Future = field(default_factory=Future, init=False, repr=False)
    # who posted it: a browser tab's id (`app.page.viewer.Viewer.origin`), None for the HTTP API; the episodes and
    # worlds it makes carry it, so each tab knows its own from those started elsewhere
    origin: str | None = field(default=None, kw_only=True)


@dataclass
class ShowEnv(Command):
    env_id: int


@dataclass
class StartEpisode(Command):
    env_id: int
    instruction: str | None = None  # None: the environment's own instruction
    policy: str = "model"  # "model", "mirror" (the model as a mirror ensemble) or "expert"
    checkpoint: str | None = None  # None: the default checkpoint
    preempt: bool = False  # end the live episode and fly this one now (the page); else queue it (the API)
    paused: bool = False  # stop after the first step (single-stepping from the start)
    world_edits: tuple = ()  # gsmn.task.edits.WorldEdit: the world flown is the environment's with these edits
    intervention: Any = None  # gsmn.analysis.intervention.Intervention: the model flies with this map from the start


@dataclass
class Pause(Command):
    pass


@dataclass
class Resume(Command):
    pass


@dataclass
class StepOnce(Command):
    pass


@dataclass
class Cancel(Command):
    pass


@dataclass
class CancelEpisode(Command):
    episode_id: int  # a queued episode is dropped from the queue, the live one ends


@dataclass
class SetSpeed(Command):
    steps_per_second: float | None  # None: as fast as it goes


@dataclass
class Ground(Command):
    episode_id: int
    text: str
    step: int | None = None  # None: the latest recorded step


# -- results --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class WorldShown:
    world: WorldSpec
    task: Task | None  # the environment's own task (None if it has no demonstration path)
    image: np.ndarray  # the first camera image
    position: tuple[float, float, float]
    yaw: float
    T_world_camera: np.ndarray
    origin: str | None = None  # the tab that asked for it (None: the API, or the server at start)


@dataclass(frozen=True)
class Grounding:
    """An instruction grounded on an episode's semantic map at one step, without flying (counterfactual)."""

    episode_id: int
    step: int
    instruction: Instruction
    relevance_w: np.ndarray  # (3, n, n) float32
    goal_w: np.ndarray  # (2, n, n)
    goal_r: np.ndarray  # (2, 2n, 2n)
    v: float  # the action the model would take (m/s, rad/s) and its STOP probability
    omega: float
    stop_probability: float
    seconds: float  # time the grounding itself took


@dataclass(frozen=True)
class CheckpointInfo:
    name: str
    path: str
    kind: str | None
    created: str | None
    loaded: bool
    default: bool
    error: str | None = None
    metrics: dict = field(default_factory=dict)
    label: str = ""  # readable: "GSMN without J_ground (Table 2: 52.0 % on 300 dev)"; the name where none is known


class RunnerListener:
    """What the runner tells the viewer. Called on the runner thread: return quickly."""

    def on_world(self, shown: WorldShown) -> None: ...

    def on_episode_start(self, episode: Episode) -> None: ...

    def on_step(self, episode: Episode, record: StepRecord) -> None: ...

    def on_episode_end(self, episode: Episode) -> None: ...

    def on_state(self, episode: Episode | None, paused: bool) -> None: ...

    def on_speed(self, steps_per_second: float | None) -> None: ...
