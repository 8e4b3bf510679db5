"""Evaluation metrics as small pure functions over episode records (paper: Evaluation Metric).

Success: the final position is within 6 m of the named landmark's centre AND in the quadrant around it that
the instruction names. Quadrants are taken with respect to the start: with d = landmark - start and
v = final - landmark, the 90-degree sector around d is "back" (beyond the landmark), the one around -d is
"front" (between the start and the landmark), and "left"/"right" are as seen from the start looking at the
landmark (left = counter-clockwise of d, since x is east, y north, z up). This matches the goal placement
in `gsmn.task.instructions`, so every goal lies on its quadrant's bisector.

Boundaries (the paper does not say): a point exactly at 45 degrees belongs to front/back (closed sectors),
a point exactly at the landmark centre is "back", and the landmark region is open as in the paper ("less
than a threshold"): a point exactly 6 m away is not inside it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np


def side_of(landmark_xy: Any, start_xy: Any, point_xy: Any) -> str:
    """The quadrant ("left", "right", "front", "back") of a point around a landmark, w.r.t. the start."""
    lx, ly = float(landmark_xy[0]), float(landmark_xy[1])
    dx, dy = lx - float(start_xy[0]), ly - float(start_xy[1])  # d, not normalised: only signs matter
    vx, vy = float(point_xy[0]) - lx, float(point_xy[1]) - ly
    along = dx * vx + dy * vy  # |d||v| cos(angle)
    across = dx * vy - dy * vx  # |d||v| sin(angle), > 0: counter-clockwise of d, i.e. on the left
    if along >= abs(across):
        return "back"
    if -along >= abs(across):
        return "front"
    return "left" if across > 0 else "right"


def landmark_success(final_xy: Any, landmark_xy: Any, radius: float = 6.0) -> bool:
    """Stopped in the target landmark region (closer than `radius` to its centre), on any side."""
    return math.dist(_xy(final_xy), _xy(landmark_xy)) < radius


def success(final_xy: Any, landmark_xy: Any, start_xy: Any, side: str, radius: float = 6.0) -> bool:
    """Stopped in the landmark region and in the quadrant the instruction names."""
    return landmark_success(final_xy, landmark_xy, radius) and side_of(landmark_xy, start_xy, final_xy) == side


def steps_in_success_region(positions: Iterable[Any], landmark_xy: Any, start_xy: Any, side: str,
                            radius: float = 6.0) -> list[int]:
    """The indices of the positions (one per step) at which a STOP would have succeeded: a policy that passes
    through the success region without saying STOP fails on its stopping, not on its navigation."""
    return [i for i, p in enumerate(positions) if success(p, landmark_xy, start_xy, side, radius)]


def record_region_steps(record: Mapping[str, Any], radius: float = 6.0) -> list[int]:
    """`steps_in_success_region` of an episode record as `EpisodeRecord.to_dict()` (or `gsmn eval --json`) has it."""
    return steps_in_success_region(record["trajectory"], (record["landmark_x"], record["landmark_y"]),
                                   (record["start_x"], record["start_y"]), record["side"], radius)


def region_stop_probability(record: Mapping[str, Any], region: list[int] | None) -> float | None:
    """The highest P(stop) the policy acted on at the steps `region` (from `record_region_steps`), or None when the
    record carries no P(stop) (the expert, a heuristic baseline, a file written before it was recorded) or the
    drone never entered the region."""
    probabilities = record.get("stop_probabilities")
    if not probabilities or not region or max(region) >= len(probabilities):
        return None
    return float(max(probabilities[i] for i in region))


def sign_test(a: int, b: int) -> float:
    """Two-sided exact sign test of a against b discordant pairs (episodes only one of two evaluations won)."""
    k, n = min(a, b), a + b
    return min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n) if n else 1.0


Z95 = 1.959963984540054  # the normal quantile of a two-sided 95 % interval


def wilson(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval of a rate (as fractions), (0, 1) for no episodes."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return max(0.0, centre - half), min(1.0, centre + half)


def goal_distance(final_xy: Any, goal_xy: Any) -> float:
    """Distance from the final position to the demonstration's goal (m)."""
    return math.dist(_xy(final_xy), _xy(goal_xy))


def _xy(p: Any) -> tuple[float, float]:
    return float(p[0]), float(p[1])


@dataclass(frozen=True)
class EpisodeOutcome:
    """What the metrics need to know about one finished episode (world frame, metres)."""

    final_x: float
    final_y: float
    landmark_x: float
    landmark_y: float
    start_x: float
    start_y: float
    side: str
    goal_x: float
    goal_y: float
    ambiguous: bool

    @classmethod
    def of(cls, world: Any, instruction: Any, final_xy: Any) -> EpisodeOutcome:
        """Build from a `WorldSpec`, an `Instruction` and the final position."""
        lm = world.landmarks[instruction.landmark_index]
        return cls(final_x=float(final_xy[0]), final_y=float(final_xy[1]), landmark_x=lm.x, landmark_y=lm.y,
                   start_x=world.start_x, start_y=world.start_y, side=instruction.side,
                   goal_x=instruction.goal_x, goal_y=instruction.goal_y, ambiguous=instruction.ambiguous)


@dataclass(frozen=True)
class Summary:
    """Aggregate metrics over a set of episodes; percentages in [0, 100], distances in metres."""

    count: int
    success: float
    landmark_success: float
    mean_distance: float
    median_distance: float
    pruned: Summary | None = None  # the same on the unambiguous episodes only

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _get(record: Any, name: str) -> Any:
    return record[name] if isinstance(record, dict) else getattr(record, name)


def summarize(records: Iterable[Any], radius: float = 6.0) -> Summary:
    """Success %, landmark success %, mean and median goal distance; also on the pruned (unambiguous) subset.

    `records` are `EpisodeOutcome`s or any objects or dicts with the same fields. Empty sets give NaN.
    """
    records = list(records)
    unambiguous = [r for r in records if not _get(r, "ambiguous")]
    return _summary(records, radius, pruned=_summary(unambiguous, radius))


def _summary(records: list[Any], radius: float, pruned: Summary | None = None) -> Summary:
    ok, lm_ok, dist = [], [], []
    for r in records:
        final = (_get(r, "final_x"), _get(r, "final_y"))
        landmark = (_get(r, "landmark_x"), _get(r, "landmark_y"))
        start = (_get(r, "start_x"), _get(r, "start_y"))
        ok.append(success(final, landmark, start, _get(r, "side"), radius))
        lm_ok.append(landmark_success(final, landmark, radius))
        dist.append(goal_distance(final, (_get(r, "goal_x"), _get(r, "goal_y"))))
    if not records:
        nan = float("nan")
        return Summary(count=0, success=nan, landmark_success=nan, mean_distance=nan, median_distance=nan,
                       pruned=pruned)
    return Summary(count=len(records), success=100.0 * float(np.mean(ok)),
                   landmark_success=100.0 * float(np.mean(lm_ok)), mean_distance=float(np.mean(dist)),
                   median_distance=float(np.median(dist)), pruned=pruned)
