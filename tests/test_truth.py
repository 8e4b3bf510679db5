"""The ground truth under the maps and the agreement figures (gsmn.analysis.truth), on hand-built maps of a real
world: a perfect map scores 1, a wrong one low; and when each stage went wrong for good."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gsmn.analysis.truth import Agreement, agreement, auc, first_failures, truth_maps
from gsmn.attribution import Heads, cell_centre, failed_from
from gsmn.config import preset
from gsmn.task.metrics import success
from gsmn.task.rollout import task_for_env
from gsmn.world.catalogue import CATALOGUE

pytestmark = pytest.mark.unit

N = 32
K = len(CATALOGUE)


@pytest.fixture(scope="module")
def case():
    config = preset("tiny")
    task = task_for_env(70, config)
    truth = truth_maps(task.world, task.instruction, N, config.task.success_radius)
    # identity heads: the perception head reads a one-hot class feature, the binary heads read channel 0
    heads = Heads(np.eye(K, dtype=np.float32), np.zeros(K, np.float32),
                  np.array([[0, 0, 0], [1, 0, 0]], np.float32), np.zeros(2, np.float32),
                  np.array([[0, 0], [1, 0]], np.float32), np.zeros(2, np.float32))
    return task, truth, heads


def semantic(truth, classes_at, seen) -> np.ndarray:
    m = np.zeros((K, N, N), np.float32)
    for r, c in zip(*np.nonzero(seen), strict=True):
        m[classes_at(r, c), r, c] = 5.0
        m[(classes_at(r, c) + 1) % K, r, c] += 0.1  # never exactly zero where seen
    return m


def test_truth_maps_follow_the_world_spec(case):
    task, truth, _ = case
    world, instruction = task.world, task.instruction
    target = world.landmarks[instruction.landmark_index]
    r, c = np.nonzero(truth.landmark == instruction.landmark_index)
    assert r.size > 0
    for rr, cc in zip(r, c, strict=True):
        x, y = cell_centre(rr, cc, world.field_size, N)
        assert np.hypot(x - target.x, y - target.y) <= target.radius
    assert truth.named[truth.landmark == instruction.landmark_index].all()
    assert (truth.class_id[truth.landmark >= 0] >= 0).all() and (truth.class_id[truth.landmark < 0] == -1).all()
    gr, gc = truth.goal_cell
    assert truth.region[gr, gc]  # the goal is in its own success region
    assert truth.region.sum() > 10
    for rr, cc in zip(*np.nonzero(truth.region), strict=True):
        x, y = cell_centre(rr, cc, world.field_size, N)
        assert success((x, y), target.position, world.start_position, instruction.side)


def test_a_perfect_map_scores_one_and_a_wrong_one_low(case):
    task, truth, heads = case
    seen = np.ones((N, N), bool)
    seen[:, : N // 4] = False  # part of the field never seen
    right = semantic(truth, lambda r, c: max(int(truth.class_id[r, c]), 0), seen)
    wrong = semantic(truth, lambda r, c: (max(int(truth.class_id[r, c]), 0) + 7) % K, seen)
    relevance = np.zeros((3, N, N), np.float32)
    relevance[0] = np.where(truth.named, 5.0, -5.0)
    goal = np.zeros((2, N, N), np.float32)
    goal[0] = np.where(truth.region, 10.0, -10.0)

    perfect = agreement(right, relevance, goal, truth, heads)
    assert perfect.perception == 1.0 and perfect.relevance == 1.0 and perfect.goal > 0.99
    assert perfect.seen_landmark_cells == int((seen & (truth.class_id >= 0)).sum())

    bad = agreement(wrong, -relevance, -goal, truth, heads)
    assert bad.perception == 0.0 and bad.relevance == 0.0 and bad.goal < 0.01

    flat = agreement(right, np.zeros_like(relevance), np.zeros_like(goal), truth, heads)
    assert flat.relevance == 0.5  # cannot tell the footprint from the rest
    assert flat.goal == pytest.approx(truth.region.sum() / N**2)  # spread evenly: the region's share

    nothing = agreement(np.zeros_like(right), relevance, goal, truth, heads)
    assert nothing.perception is None and nothing.relevance is None  # nothing seen yet

    untrained = Heads(*(getattr(heads, f) for f in ("perception_w", "perception_b", "grounding_w", "grounding_b",
                                                     "goal_w", "goal_b")), goal_trained=False)
    assert agreement(right, relevance, goal, truth, untrained).goal is None
    no_percept = dataclasses.replace(heads, perception_trained=False)
    no_ground = dataclasses.replace(heads, grounding_trained=False)
    assert agreement(right, relevance, goal, truth, no_percept).perception is None
    assert agreement(right, relevance, goal, truth, no_percept).relevance == 1.0
    assert agreement(right, relevance, goal, truth, no_ground).relevance is None
    assert agreement(right, relevance, goal, truth, no_ground).perception == 1.0
    figures = np.array([[1.0, 1.0, 0.9, 0.03], [0.0, 0.0, 0.0, 0.03]], np.float32)
    assert set(failed_from(figures)) == {"perception", "grounding", "goal"}
    assert set(failed_from(figures, no_ground)) == {"perception", "goal"}
    assert set(failed_from(figures, no_percept)) == {"grounding", "goal"}


def test_auc_counts_ties_half():
    assert auc([3, 4], [1, 2]) == 1.0
    assert auc([1, 2], [3, 4]) == 0.0
    assert auc([1, 1], [1, 1]) == 0.5
    assert auc([2, 1], [1, 0]) == pytest.approx((1 + 1 + 0.5 + 1) / 4)
    assert auc([], [1]) is None


def test_first_failures_is_where_a_figure_went_below_for_good():
    def a(p, r, g):
        return Agreement(p, r, g, 0, 0.03)

    # region share 0.03: the goal figure is wrong at or below 0.06
    figures = [a(None, None, 0.01), a(0.1, 0.9, 0.2), a(0.8, 0.9, 0.2), a(0.8, 0.5, 0.2), a(0.9, 0.4, 0.05)]
    assert first_failures(figures) == {"perception": None, "relevance": 3, "goal": 4}
    assert first_failures([a(None, None, None)]) == {"perception": 0, "relevance": 0, "goal": 0}
    assert first_failures([]) == {"perception": None, "relevance": None, "goal": None}
