"""The expert: a carrot planner that follows a demonstration path (paper: Data and Systems, "Oracle";
control law and numbers from the original code).

At each step the drone is projected onto the path (progress), the carrot is the point 12 waypoints
(about 14 m) further along (shrinking to the goal near the end), and

    v_norm     = clip((progress + 1) / 3, 0.1, 1)                ramp over the first 3 waypoints
    omega_norm = clip(0.5 * heading_error - 0.1 * lateral_error, -1, 1)

with the heading error to the carrot in radians and the lateral error the signed distance (m) from the
path, positive to the left of it (the original's units for this term are not known; we take metres,
so 1 m off the path adds 0.24 rad/s). Physical commands are the normalised ones times the drone's limits
(1.6 m/s, 2.44 rad/s). STOP once progress reaches the second-to-last waypoint and the drone is within
`stop_radius` (1.8 m) of the goal.

Departure, the stop radius: the original stops on progress alone. On the path the two agree (progress at the
second-to-last waypoint is at most a spacing, 1.2 m, from the goal). Off it, as in DAgger's learner states,
progress is the projection onto the path, and a learner flying past a landmark's side while the path curls
around its rim to the back reaches the stop waypoint's projection 2.5-5 m from the goal, often in the wrong
quadrant: in the test rollouts of an earlier GSMN, 65 of 236 first expert STOPs along the learner's path were
outside the success region (docs/design.md, "Departure: the expert stops only near the goal"). Those labels
taught the learner to stop short of and beside back-side goals. With the radius, the expert keeps flying to
the goal (the carrot is the goal near the end) until it is close.

Progress is monotone non-decreasing and searched only `progress_window` waypoints ahead of its last value,
so the expert never jumps back (or far forward) across a loop of the path, and it answers from anywhere,
as DAgger needs. Departure: progress is the continuous projection onto the path's segments (waypoint
index plus fraction), not the nearest waypoint index. With the nearest index, "reaching" the second-to-
last waypoint would mean being half a spacing short of it, so the expert would stop about 0.6 m earlier.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gsmn.config import DroneConfig, ExpertConfig


@dataclass(frozen=True)
class ExpertAction:
    forward_velocity: float  # m/s
    yaw_rate: float  # rad/s, positive turns left
    stop: bool
    v_norm: float  # forward_velocity / max_forward_velocity, in [0, 1]: the model's label
    omega_norm: float  # yaw_rate / max_yaw_rate, in [-1, 1]: the model's label
    progress: float  # position along the path in waypoints (index + fraction)


def wrap_angle(a: float) -> float:
    """An angle in [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


class Expert:
    """Carrot planner over a fixed path (N, 2). Holds the progress across steps; `reset` clears it."""

    def __init__(self, path: np.ndarray, config: ExpertConfig | None = None,
                 drone_config: DroneConfig | None = None):
        self.path = np.asarray(path, dtype=float)  # (N, 2)
        if self.path.ndim != 2 or self.path.shape[1] != 2 or len(self.path) < 2:
            raise ValueError(f"a path needs shape (N >= 2, 2), got {self.path.shape}")
        self.config = config or ExpertConfig()
        self.drone_config = drone_config or DroneConfig()
        self.progress = 0.0

    def reset(self) -> None:
        self.progress = 0.0

    @property
    def stop_progress(self) -> int:
        """The waypoint index at which the expert stops (second-to-last by default)."""
        return max(len(self.path) - 1 - self.config.stop_before_end, 0)

    def act(self, position_xy: np.ndarray, yaw: float) -> ExpertAction:
        """The expert's action from the drone's position (x, y) and heading; advances the progress."""
        c, p = self.config, np.asarray(position_xy, dtype=float)[:2]
        self.progress, lateral_error = self._project(p)
        if self.progress >= self.stop_progress and math.dist(p, self.path[-1]) <= c.stop_radius:
            return ExpertAction(0.0, 0.0, True, 0.0, 0.0, self.progress)
        carrot = self.point_at(self.progress + c.look_ahead)
        to_carrot = carrot - p
        heading_error = wrap_angle(math.atan2(to_carrot[1], to_carrot[0]) - yaw)
        # As the original: (index + 1) / 3, so the drone starts at a third of full speed.
        ramp = (self.progress + 1) / c.ramp_waypoints if c.ramp_waypoints > 0 else 1.0
        v_norm = float(np.clip(ramp, c.min_speed, 1.0))
        omega_norm = float(np.clip(c.heading_gain * heading_error - c.lateral_gain * lateral_error, -1.0, 1.0))
        d = self.drone_config
        return ExpertAction(v_norm * d.max_forward_velocity, omega_norm * d.max_yaw_rate, False, v_norm,
                            omega_norm, self.progress)

    def _project(self, p: np.ndarray) -> tuple[float, float]:
        """Monotone progress (waypoints) and signed lateral error (m, > 0 left of the path) of point p."""
        first = min(int(self.progress), len(self.path) - 2)
        last = min(first + self.config.progress_window, len(self.path) - 2)
        a, b = self.path[first:last + 1], self.path[first + 1:last + 2]  # (S, 2) segments
        ab = b - a
        t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0, 1)
        foot = a + t[:, None] * ab
        k = int(np.argmin(np.linalg.norm(p - foot, axis=1)))
        progress = max(self.progress, first + k + float(t[k]))
        # Signed distance to the (infinite) line of the nearest segment: left of the path is positive.
        direction = ab[k] / max(float(np.linalg.norm(ab[k])), 1e-12)
        offset = p - a[k]
        lateral_error = float(direction[0] * offset[1] - direction[1] * offset[0])
        return progress, lateral_error

    def point_at(self, progress: float) -> np.ndarray:
        """The point of the path at a fractional waypoint index, clipped to the path's ends."""
        progress = float(np.clip(progress, 0, len(self.path) - 1))
        i = min(int(progress), len(self.path) - 2)
        return self.path[i] + (progress - i) * (self.path[i + 1] - self.path[i])

    def distance_to_path(self, position_xy: np.ndarray) -> float:
        """Distance (m) from a point to the nearest point of the whole path (DAgger cuts rollouts on it)."""
        p = np.asarray(position_xy, dtype=float)[:2]
        a, b = self.path[:-1], self.path[1:]
        ab = b - a
        t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0, 1)
        return float(np.min(np.linalg.norm(p - (a + t[:, None] * ab), axis=1)))
