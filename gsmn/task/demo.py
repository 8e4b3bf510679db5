"""Ground-truth demonstration paths (paper: Data, "simulating a point-mass attracted to the goal with
landmark avoidance constraints"; numbers from the original code).

The path starts at the start position with a straight 2.4 m take-off along the start heading. Then a point
mass moves 0.12 m per step straight toward the goal until it is within 0.6 m of it; the goal itself ends the
path. The dense trace is resampled to a waypoint every 1.2 m. A path is rejected (`DemoPathError`) if the
point mass needs more than 500 steps, or the path leaves the field or crosses itself.

Landmark avoidance. The original pushes the point mass out of every landmark's radius. A pure radial
push-out stalls when a landmark lies straight in the way (the step toward the goal and the push cancel), so
we depart: when a step would end inside a landmark's radius, the point mass instead slides one step along
the rim of that landmark - tangentially, toward the side of the line (centre, point mass) that the goal is
on (counter-clockwise on an exact tie) - and is put back onto the rim. If going around that way leaves the
field (landmarks can stand closer to the edge than their radius), the path is redone going around that
landmark the other way; only if both ways fail is the path rejected. The push-out radius is the
landmark's radius itself, with no margin: the goal lies exactly on the named landmark's rim, so the point
mass can still reach it (sliding along the rim for the last metres if needed). Only the straight chords
between waypoints on a rim dip inside a radius, by at most spacing^2 / (8 r) < 0.08 m.
"""

from __future__ import annotations

import math

import numpy as np

from gsmn.config import ExpertConfig
from gsmn.world.spec import WorldSpec


class DemoPathError(ValueError):
    """No acceptable demonstration path (too long, leaves the field, or crosses itself)."""


def demonstration_path(world: WorldSpec, goal_xy: np.ndarray, config: ExpertConfig | None = None) -> np.ndarray:
    """Waypoints (N, 2) from the start to `goal_xy`, `config.waypoint_spacing` apart; the last is the goal."""
    config = config or ExpertConfig()
    goal = np.asarray(goal_xy, dtype=float)
    if not world.on_field(goal):
        raise DemoPathError(f"environment {world.env_id}: the goal {goal.round(2).tolist()} is outside the field")
    flipped: set[int] = set()
    while True:
        try:
            trace = _point_mass_trace(world, goal, config, flipped)
            break
        except _LeftField as e:
            if e.landmark is None or e.landmark in flipped:
                raise DemoPathError(f"environment {world.env_id}: the demonstration leaves the field") from None
            flipped.add(e.landmark)  # go around this landmark the other way
    path = resample(trace, config.waypoint_spacing)
    if crosses_itself(path):
        raise DemoPathError(f"environment {world.env_id}: the demonstration crosses itself")
    return path


class _LeftField(Exception):
    def __init__(self, landmark: int | None):
        self.landmark = landmark  # the landmark being slid around when it happened, if any


def _point_mass_trace(world: WorldSpec, goal: np.ndarray, config: ExpertConfig, flipped: set[int]
                      ) -> np.ndarray:
    """Dense trace (M, 2): start, end of take-off, every point-mass position, goal.

    `flipped`: landmarks to slide around away from the goal's side (the goal's side left the field).
    """
    start = world.start_position
    heading = np.array([math.cos(world.start_yaw), math.sin(world.start_yaw)])
    pos = start + config.takeoff_distance * heading
    trace = [start, pos]
    centres = np.array([lm.position for lm in world.landmarks]).reshape(-1, 2)  # (K, 2)
    radii = np.array([lm.radius for lm in world.landmarks])  # (K,)
    contact: tuple[int, float] | None = None  # (landmark, +1 counter-clockwise / -1) while sliding on a rim
    for _ in range(config.max_demo_steps):
        to_goal = goal - pos
        dist = float(np.linalg.norm(to_goal))
        if dist <= config.target_tolerance:
            trace.append(goal)
            return np.array(trace)
        new = pos + min(config.demo_step, dist) * to_goal / dist
        inside = np.flatnonzero(np.linalg.norm(new - centres, axis=1) < radii)
        if inside.size == 0:
            contact = None
        else:
            k = int(inside[0])
            if contact is None or contact[0] != k:
                # Slide toward the side of the line (centre, point mass) that the goal is on; keep that
                # direction until the contact ends, so a flipped landmark is not re-decided every step.
                goal_side = 1.0 if _cross(pos - centres[k], goal - centres[k]) >= 0 else -1.0
                contact = (k, -goal_side if k in flipped else goal_side)
            new = _slide(pos, centres[k], radii[k], config.demo_step, contact[1])
        if not world.on_field(new):
            raise _LeftField(None if contact is None else contact[0])
        trace.append(new)
        pos = new
    raise DemoPathError(f"environment {world.env_id}: the point mass did not reach the goal in "
                        f"{config.max_demo_steps} steps")


def _slide(pos: np.ndarray, centre: np.ndarray, radius: float, step: float, direction: float) -> np.ndarray:
    """One step along the rim of a landmark (direction +1 counter-clockwise); the result lies on the rim."""
    normal = (pos - centre) / np.linalg.norm(pos - centre)
    tangent = direction * np.array([-normal[1], normal[0]])
    new = pos + step * tangent
    return centre + radius * (new - centre) / np.linalg.norm(new - centre)


def resample(trace: np.ndarray, spacing: float) -> np.ndarray:
    """Points (N, 2) every `spacing` metres along a polyline (M, 2), plus its last point."""
    seg = np.linalg.norm(np.diff(trace, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])  # (M,) arc length
    total = s[-1]
    targets = np.arange(0.0, total, spacing)
    if total - targets[-1] > 1e-6:
        targets = np.append(targets, total)
    else:
        targets[-1] = total
    return np.stack([np.interp(targets, s, trace[:, 0]), np.interp(targets, s, trace[:, 1])], axis=1)


def crosses_itself(path: np.ndarray, eps: float = 1e-9) -> bool:
    """Whether any two non-adjacent segments of a polyline (N, 2) intersect or touch."""
    a, r = path[:-1], np.diff(path, axis=0)  # (S, 2) segment starts and directions
    for i in range(len(a) - 2):
        q, s = a[i + 2:], r[i + 2:]  # segments j >= i + 2
        denom = _cross(r[i], s)
        qp = q - a[i]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = _cross(qp, s) / denom  # along segment i
            u = _cross(qp, r[i]) / denom  # along segment j
        parallel = np.abs(denom) <= eps * np.linalg.norm(r[i]) * np.linalg.norm(s, axis=1)
        hit = ~parallel & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
        # Parallel segments meet only if collinear and overlapping (the path retraces itself).
        rr = max(float(r[i] @ r[i]), eps)
        collinear = parallel & (np.abs(_cross(qp, r[i])) <= 1e-6 * np.sqrt(rr))
        t0, t1 = (qp @ r[i]) / rr, ((qp + s) @ r[i]) / rr
        overlap = collinear & (np.maximum(t0, t1) >= 0) & (np.minimum(t0, t1) <= 1)
        if np.any(hit | overlap):
            return True
    return False


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def path_length(path: np.ndarray) -> float:
    """Length (m) of a polyline (N, 2)."""
    return float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))
