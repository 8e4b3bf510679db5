"""World specification and procedural sampling (paper: Experimental Setup / Environment).

The world is data first: `sample_world(config, rng) -> WorldSpec` draws a field of landmarks, lakes
and a start pose from an injected `numpy.random.Generator`; `world_for_env(env_id)` seeds that
generator from the environment id so every id always gives the same world. The simulator, the expert,
the metrics, the labels and the dashboard all read the WorldSpec, never the compiled MuJoCo model.

Placement rules (paper and original code): landmark centres inside [2.7 m, 27.3 m]^2, at least
r_i + r_j + 1.8 m apart, at least r + 4.5 m from the start; the start at one of the four corners facing
45 deg into the field. The paper draws 6 to 13 landmarks; at these radii 11 or more rarely fit under the
gap rule, so landmarks that find no free spot are dropped (at least `min_landmarks` are kept, else the
world is redrawn). docs/design.md records the resulting counts.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass

import numpy as np

from gsmn.config import WorldConfig
from gsmn.world.catalogue import CATALOGUE

SPLITS = ("train", "test", "dev")


def split_of(env_id: int) -> str:
    """The split of an environment id, as in the original: id % 100 in 0-69 train, 70-84 test, 85-99 dev."""
    if env_id < 0:
        raise ValueError(f"environment ids are non-negative, got {env_id}")
    r = env_id % 100
    return "train" if r < 70 else ("test" if r < 85 else "dev")


def on_field(x: float, y: float, field_size: float) -> bool:
    """Whether the point (x, y) lies on the field, the square [0, field_size]^2 (its edges included)."""
    return 0.0 <= x <= field_size and 0.0 <= y <= field_size


def split_env_ids(split: str, count: int, start: int = 0) -> list[int]:
    """The first `count` environment ids of a split, at or after `start`."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; choose from {SPLITS}")
    out, env_id = [], start
    while len(out) < count:
        if split_of(env_id) == split:
            out.append(env_id)
        env_id += 1
    return out


@dataclass(frozen=True)
class LandmarkSpec:
    model: str  # catalogue name, e.g. "fir_tree"
    noun_phrase: str  # e.g. "fir tree"
    class_id: int  # index into CATALOGUE
    x: float
    y: float
    yaw: float  # rotation of the model about z (rad)
    scale: float  # uniform mesh scale, U(radius_scale_min, radius_scale_max)
    radius: float  # scaled radius class (m): goals sit this far from the centre

    @property
    def position(self) -> np.ndarray:
        return np.array([self.x, self.y])


@dataclass(frozen=True)
class LakeSpec:
    """A decorative lake: a flat ellipse on the ground. Not a landmark."""

    x: float
    y: float
    radius_x: float
    radius_y: float
    yaw: float


@dataclass(frozen=True)
class WorldSpec:
    env_id: int
    field_size: float
    landmarks: tuple[LandmarkSpec, ...]
    lakes: tuple[LakeSpec, ...]
    start_corner: int  # 0: (0, 0), 1: (L, 0), 2: (L, L), 3: (0, L)
    start_x: float
    start_y: float
    start_yaw: float  # heading (rad), 45 deg into the field

    @property
    def split(self) -> str:
        return split_of(self.env_id)

    @property
    def start_position(self) -> np.ndarray:
        return np.array([self.start_x, self.start_y])

    def on_field(self, xy) -> bool:
        """Whether the point `xy` (x, y) lies on this world's field (edges included)."""
        return on_field(float(xy[0]), float(xy[1]), self.field_size)

    def landmarks_named(self, noun_phrase: str) -> tuple[LandmarkSpec, ...]:
        return tuple(lm for lm in self.landmarks if lm.noun_phrase == noun_phrase)

    def to_dict(self) -> dict:
        return asdict(self)

    def to_json(self, indent: int | None = 1) -> str:
        return json.dumps(self.to_dict(), indent=indent)

    @classmethod
    def from_dict(cls, d: dict) -> WorldSpec:
        d = dict(d)
        d["landmarks"] = tuple(LandmarkSpec(**lm) for lm in d["landmarks"])
        d["lakes"] = tuple(LakeSpec(**lk) for lk in d["lakes"])
        return cls(**d)


def start_pose(corner: int, field_size: float) -> tuple[float, float, float]:
    """Position and heading of a start corner, facing 45 deg into the field."""
    x = field_size if corner in (1, 2) else 0.0
    y = field_size if corner in (2, 3) else 0.0
    yaw = math.atan2(field_size / 2 - y, field_size / 2 - x)
    return x, y, yaw


def rng_for_env(env_id: int, seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, env_id]))


def world_for_env(env_id: int, config: WorldConfig | None = None) -> WorldSpec:
    """The world of an environment id: deterministic for (config, env_id)."""
    config = config or WorldConfig()
    if env_id < 0:
        raise ValueError(f"environment ids are non-negative, got {env_id}")
    return sample_world(config, rng_for_env(env_id, config.seed), env_id=env_id)


def sample_world(config: WorldConfig, rng: np.random.Generator, env_id: int = -1) -> WorldSpec:
    """Draw a world: start corner, landmarks (placement rules above) and decorative lakes."""
    L = config.field_size
    corner = int(rng.integers(4))
    sx, sy, syaw = start_pose(corner, L)
    start = np.array([sx, sy])
    while True:
        landmarks = _place_landmarks(config, rng, start)
        if len(landmarks) >= config.min_landmarks:
            break
    lakes = _place_lakes(config, rng, start, landmarks)
    return WorldSpec(env_id=env_id, field_size=L, landmarks=tuple(landmarks), lakes=tuple(lakes),
                     start_corner=corner, start_x=sx, start_y=sy, start_yaw=syaw)


def _place_landmarks(config: WorldConfig, rng: np.random.Generator, start: np.ndarray) -> list[LandmarkSpec]:
    n = int(rng.integers(config.min_landmarks, config.max_landmarks + 1))
    class_ids = rng.choice(len(CATALOGUE), size=n, replace=False)
    scales = rng.uniform(config.radius_scale_min, config.radius_scale_max, size=n)
    yaws = rng.uniform(-math.pi, math.pi, size=n)
    lo, hi = config.edge_margin, config.field_size - config.edge_margin
    placed: list[LandmarkSpec] = []
    for class_id, scale, yaw in zip(class_ids, scales, yaws, strict=True):
        model = CATALOGUE[class_id]
        radius = model.radius * scale
        candidates = rng.uniform(lo, hi, size=(config.placement_candidates, 2))  # (N, 2)
        ok = np.linalg.norm(candidates - start, axis=1) >= radius + config.start_clearance
        for other in placed:
            gap = radius + other.radius + config.landmark_gap
            ok &= np.linalg.norm(candidates - other.position, axis=1) >= gap
        free = np.flatnonzero(ok)
        if free.size == 0:
            continue  # no room left for this one: dropped (see module docstring)
        x, y = candidates[free[0]]
        placed.append(LandmarkSpec(model=model.name, noun_phrase=model.noun_phrase, class_id=int(class_id),
                                   x=float(x), y=float(y), yaw=float(yaw), scale=float(scale),
                                   radius=float(radius)))
    return placed


def _place_lakes(config: WorldConfig, rng: np.random.Generator, start: np.ndarray,
                 landmarks: list[LandmarkSpec]) -> list[LakeSpec]:
    """Decorative lakes in the space the landmarks leave, clear of landmark radii and the start."""
    n = int(rng.integers(config.min_lakes, config.max_lakes + 1))
    lakes: list[LakeSpec] = []
    for _ in range(n):
        rx, ry = rng.uniform(config.lake_radius_min, config.lake_radius_max, size=2)
        yaw = float(rng.uniform(0, math.pi))
        extent = max(rx, ry)
        candidates = rng.uniform(extent, config.field_size - extent, size=(200, 2))
        ok = np.linalg.norm(candidates - start, axis=1) >= extent + 3.0
        for lm in landmarks:
            ok &= np.linalg.norm(candidates - lm.position, axis=1) >= extent + lm.radius
        for lk in lakes:
            ok &= np.linalg.norm(candidates - np.array([lk.x, lk.y]), axis=1) >= (
                extent + max(lk.radius_x, lk.radius_y) + 1.0)
        free = np.flatnonzero(ok)
        if free.size:
            x, y = candidates[free[0]]
            lakes.append(LakeSpec(x=float(x), y=float(y), radius_x=float(rx), radius_y=float(ry), yaw=yaw))
    return lakes
