"""Episodes as the dashboard keeps them: every step's pose, action, camera image (JPEG) and the model's maps
(float16), in memory, so the timeline can scrub a finished episode and the API can serve per-step data and
counterfactual grounding at any step. Episodes are kept up to a limit; the oldest finished ones are dropped.

Written only by the runner thread; read by the viewer and the API. A step list only grows, so readers can
index it without a lock; the store's dictionary is guarded by a lock.
"""

from __future__ import annotations

import io
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from PIL import Image

from gsmn.task.metrics import side_of
from gsmn.task.rollout import EpisodeRecord, Task

QUEUED, RUNNING, PAUSED, FINISHED, CANCELLED, FAILED = "queued", "running", "paused", "finished", "cancelled", "failed"
LIVE = (QUEUED, RUNNING, PAUSED)


@dataclass(frozen=True)
class StepMaps:
    """What the model computed at one step: the maps of its output record (`GSMNOutputs.maps()`), under the
    record's names, as small float16 arrays (north-up world maps, docs/model.md), and its own action."""

    maps: dict[str, np.ndarray]  # e.g. semantic_map_w (C_f, n, n), goal_map_r (2, 2n, 2n): one step, channels first
    pose: np.ndarray  # (3,) x, y, yaw the model used (float32)
    v: float  # the model's own action (m/s, rad/s) and STOP probability at this step
    omega: float
    stop_probability: float

    @property
    def semantic_w(self) -> np.ndarray:
        """(C_f, n, n) the semantic map after this step's image."""
        return self.maps["semantic_map_w"]

    @property
    def coverage_w(self) -> np.ndarray:
        """(n, n) this step's camera coverage."""
        return self.maps["coverage_w"][0]

    @property
    def relevance_w(self) -> np.ndarray:
        """(3, n, n)"""
        return self.maps["relevance_map_w"]

    @property
    def goal_w(self) -> np.ndarray:
        """(2, n, n)"""
        return self.maps["goal_map_w"]

    @property
    def goal_r(self) -> np.ndarray:
        """(2, 2n, 2n) the goal map the controller reads (drone at the centre, facing up)."""
        return self.maps["goal_map_r"]


@dataclass(frozen=True)
class StepRecord:
    step: int
    time: float  # simulated seconds
    position: tuple[float, float, float]
    yaw: float
    T_world_camera: np.ndarray  # (4, 4) float32, camera x right, y down, z forward
    camera_jpeg: bytes
    v: float  # the action flown (m/s, rad/s) and whether it was STOP
    omega: float
    stop: bool
    maps: StepMaps | None  # None when no model watched this episode
    # the P(stop) the flown STOP was decided on when a model flew (a mirror ensemble's: the mean of its two
    # copies, where maps.stop_probability is the unmirrored copy's); None when the expert flew
    stop_probability: float | None = None
    damaged: str | None = None  # why its maps could not be read back from the record (app.jobs.kept); None: they could

    @property
    def decisive_stop_probability(self) -> float | None:
        """The P(stop) that decided this step when a model flew, else the watching model's; None without a model."""
        if self.stop_probability is not None:
            return self.stop_probability
        return self.maps.stop_probability if self.maps is not None else None


@dataclass(frozen=True)
class EpisodeResult:
    success: bool
    landmark_success: bool
    goal_distance: float  # m, final position to the demonstration's goal
    landmark_distance: float  # m, final position to the named landmark's centre
    final_side: str  # quadrant of the final position around the named landmark
    steps: int
    stopped: bool  # the policy said STOP (else the horizon ended the episode)
    final_x: float
    final_y: float
    stop_probability: float | None  # the model's P(STOP) at the last step

    @classmethod
    def of(cls, record: EpisodeRecord, stop_probability: float | None) -> EpisodeResult:
        final = (record.final_x, record.final_y)
        landmark = (record.landmark_x, record.landmark_y)
        return cls(success=record.success, landmark_success=record.landmark_success,
                   goal_distance=record.goal_distance, landmark_distance=float(np.hypot(
                       record.final_x - record.landmark_x, record.final_y - record.landmark_y)),
                   final_side=side_of(landmark, (record.start_x, record.start_y), final), steps=record.steps,
                   stopped=record.stopped, final_x=record.final_x, final_y=record.final_y,
                   stop_probability=stop_probability)


@dataclass
class Episode:
    id: int
    task: Task
    policy: str  # "model", "mirror" (the model as a mirror ensemble) or "expert"
    system: str  # what flies: the checkpoint's kind or "oracle"
    checkpoint: str | None  # the model whose maps are recorded (None: no maps)
    horizon: int
    start_paused: bool = False  # stop after the first step (single-stepping from the start)
    status: str = QUEUED
    steps: list[StepRecord] = field(default_factory=list)
    result: EpisodeResult | None = None
    error: str | None = None
    created: float = field(default_factory=time.time)
    started: float | None = None  # time.perf_counter() when the runner began flying it
    first_frame: float | None = None  # time.perf_counter() when its first step was recorded
    finished: float | None = None
    # the simulator's state at every step and the policy's every few (gsmn.task.fork), in memory, for forks
    snapshots: Any = None  # gsmn.task.fork.FlightSnapshots once it flies
    fork: Any = None  # app.live.compare.ForkPoint: where this episode forks from another (steps 0..t-1 are its)
    comparison: int | None = None  # the comparison it flies in (app.live.compare)
    compared_with: int | None = None  # the other episode of that comparison
    origin: str | None = None  # the browser tab that started it (app.live.commands.Command.origin); None: the API
    typed: str | None = None  # the instruction as typed (gsmn.task.understand); the task's is the template flown
    world_edits: tuple = ()  # gsmn.task.edits.WorldEdit: the edits its world carries (task.world is the edited one)
    intervention: Any = None  # gsmn.analysis.intervention.Intervention: the map it flew with (from its fork's step)
    intervene: Any = None  # what makes that map for the flight (app.live.flight.intervention_maker); not kept

    @property
    def env_id(self) -> int:
        return self.task.world.env_id

    @property
    def instruction(self) -> str:
        return self.task.instruction.text

    @property
    def live(self) -> bool:
        return self.status in LIVE

    @property
    def comparison_side(self) -> int | None:
        """1 for a comparison's first policy, 2 for the one compared with (a comparison's episodes are made in its
        order, so the first has the smaller id); None outside a comparison."""
        if self.comparison is None:
            return None
        return 1 if self.compared_with is None or self.id < self.compared_with else 2

    def steps_per_second(self) -> float | None:
        if self.first_frame is None or len(self.steps) < 2:
            return None
        end = self.finished or time.perf_counter()
        return (len(self.steps) - 1) / max(end - self.first_frame, 1e-9)


class EpisodeStore:
    """Episodes by id, oldest first; at most `limit` are kept, and only finished ones are dropped."""

    def __init__(self, limit: int = 16):
        if limit < 1:
            raise ValueError(f"the episode limit must be at least 1, got {limit}")
        self.limit = limit
        self._episodes: OrderedDict[int, Episode] = OrderedDict()
        self._lock = threading.Lock()
        self._next_id = 1

    def new_id(self) -> int:
        with self._lock:
            self._next_id += 1
            return self._next_id - 1

    def add(self, episode: Episode) -> None:
        with self._lock:
            self._episodes[episode.id] = episode
            done = [k for k, e in self._episodes.items() if not e.live]
            while len(self._episodes) > self.limit and done:
                del self._episodes[done.pop(0)]

    def get(self, episode_id: int) -> Episode | None:
        with self._lock:
            return self._episodes.get(episode_id)

    def missing(self, episode_id: int) -> str:
        """Why `get(episode_id)` found nothing, for the 404."""
        if episode_id >= self._next_id:
            return f"no episode {episode_id}: none has that id yet"
        return f"no episode {episode_id} (episodes are kept in memory, the oldest dropped)"

    def all(self) -> list[Episode]:
        with self._lock:
            return list(self._episodes.values())

    def __len__(self) -> int:
        with self._lock:
            return len(self._episodes)


def jpeg_bytes(image: np.ndarray, quality: int = 85) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buffer, format="JPEG", quality=quality)
    return buffer.getvalue()
