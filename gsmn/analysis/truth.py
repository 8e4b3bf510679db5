"""Ground truth under the model's maps, from the WorldSpec, and how well each map agrees with it at a step.

The truth, per world-map cell (north-up, `gsmn.model.grid`; a cell is judged by its centre):

- footprints: the landmark whose radius covers the cell (its catalogue class), or none;
- the named footprint: the cells covered by a landmark with the instruction's noun phrase (landmarks sharing the
  name all count, as the attribution's grounding test lets them);
- the success region: the cells where a STOP would succeed (within the success radius of the named landmark and in
  the quadrant asked, `gsmn.task.metrics.success`), and the goal's own cell.

The agreement figures, each in [0, 1], 1 for a perfect map:

- perception: the share of the seen landmark cells (covered by a footprint and by the camera at some step) whose
  most likely class from the perception head has the landmark's name. The head has no "no landmark" class, so
  cells outside every footprint have no right answer and are left out.
- relevance: the AUC of P(named) (the grounding head) at telling the named footprint's cells from the other seen
  cells: the chance that a footprint cell scores above a cell outside it (ties count half); 0.5 is a map that
  cannot tell them apart, 0 one that ranks them backwards. An AUC rather than an IoU: the IoU needs a threshold on
  P(named), and the grounding head is trained per cell with a class-imbalanced loss, so its probabilities are not
  calibrated (a well-placed peak of 0.3 is common); an IoU at 0.5 would call such a map empty. The AUC reads the
  ranking only, which is what the goal filter downstream uses. Unseen cells are left out: the map holds nothing
  there.
- goal: the share of the goal head's P(goal), summed over the field, that lies inside the success region.

Each is None where it is undefined (no seen landmark cell yet, no footprint cell or no other cell seen), and where
the model's head for it was never trained (the perception figure without J_percept, the relevance figure without
J_ground, the goal figure without J_plan: `gsmn.model.readout.trained_heads`).
`first_failures` turns the figures over an episode into the step at which each stage first fell below its
threshold (`gsmn.attribution` names the stage that failed; this says when).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from gsmn.model.grid import cell_centre, cell_of, observed_cells
from gsmn.model.heads import positive_probability, softmax
from gsmn.model.readout import Heads
from gsmn.task.instructions import Instruction
from gsmn.task.metrics import success
from gsmn.world.catalogue import CATALOGUE
from gsmn.world.spec import WorldSpec

# a figure at or below these is no better than chance, and its stage counts as wrong at that step (first_failures):
# perception: 0.2 (chance is 1 in 63 classes; the shipped GSMN's successes end at 0.29-0.47), relevance: an AUC of
# 0.5, goal: twice the success region's share of the field, what an even spread of P(goal) puts there (successes
# end at 4-7 times it). The shipped GSMN's figures: docs/compare.md, "Ground truth and the agreement figures".
THRESHOLDS = {"perception": 0.2, "relevance": 0.5, "goal": 2.0}  # goal: times the region's share


@dataclass(frozen=True)
class TruthMaps:
    """The truth on an n x n north-up world map."""

    landmark: np.ndarray  # (n, n) int: index into world.landmarks of the landmark covering the cell, -1: none
    class_id: np.ndarray  # (n, n) int: that landmark's catalogue class, -1: none
    named: np.ndarray  # (n, n) bool: the named landmark's footprint (every landmark of that name)
    region: np.ndarray  # (n, n) bool: a STOP here succeeds
    goal_cell: tuple[int, int]  # (row, col) of the true goal


def truth_maps(world: WorldSpec, instruction: Instruction, n: int, success_radius: float = 6.0) -> TruthMaps:
    F = world.field_size
    rows, cols = np.mgrid[0:n, 0:n]
    cx, cy = cell_centre(rows, cols, F, n)  # (n, n) each
    landmark = np.full((n, n), -1, int)
    best = np.full((n, n), np.inf)
    for i, lm in enumerate(world.landmarks):  # the nearest centre wins where footprints overlap
        d = np.hypot(cx - lm.x, cy - lm.y)
        take = (d <= lm.radius) & (d < best)
        landmark[take], best[take] = i, d[take]
    class_ids = np.array([lm.class_id for lm in world.landmarks] + [-1])
    class_id = class_ids[landmark]  # -1 indexes the sentinel
    named_ids = [i for i, lm in enumerate(world.landmarks) if lm.noun_phrase == instruction.noun_phrase]
    named = np.isin(landmark, named_ids)
    target = world.landmarks[instruction.landmark_index]
    region = np.array([[success((cx[r, c], cy[r, c]), target.position, world.start_position, instruction.side,
                                success_radius) for c in range(n)] for r in range(n)])
    return TruthMaps(landmark, class_id, named, region, cell_of(instruction.goal_x, instruction.goal_y, F, n))


@dataclass(frozen=True)
class Agreement:
    perception: float | None
    relevance: float | None
    goal: float | None
    seen_landmark_cells: int  # the cells the perception figure is over
    region_share: float = 0.03  # the success region's share of the field's cells (P(goal) spread evenly)

    def to_dict(self) -> dict:
        return asdict(self)


def perception_accuracy(semantic_w: np.ndarray, truth: TruthMaps, heads: Heads) -> tuple[float | None, int]:
    """(accuracy, cells) over the seen landmark cells (see the module docstring); accuracy None without a trained
    perception head."""
    seen = observed_cells(semantic_w) & (truth.class_id >= 0)
    count = int(seen.sum())
    if count == 0 or not heads.perception_trained:
        return None, count
    features = semantic_w[:, seen].astype(np.float32)  # (C, m)
    logits = np.einsum("kc,cm->km", heads.perception_w.astype(np.float32), features) \
        + heads.perception_b.astype(np.float32)[:, None]
    predicted = softmax(logits, axis=0).argmax(0)
    names = np.array([m.noun_phrase for m in CATALOGUE])
    right = names[predicted] == names[truth.class_id[seen]]  # classes sharing a name count as right
    return float(right.mean()), count


def auc(scores_positive: np.ndarray, scores_negative: np.ndarray) -> float | None:
    """P(a positive scores above a negative), ties half (the Mann-Whitney U over the product of the counts)."""
    p, q = np.asarray(scores_positive, float).ravel(), np.asarray(scores_negative, float).ravel()
    if p.size == 0 or q.size == 0:
        return None
    allv = np.concatenate([p, q])
    order = np.argsort(allv, kind="mergesort")
    ranks = np.empty(allv.size)
    sorted_v = allv[order]
    # average ranks of ties
    _, first, counts = np.unique(sorted_v, return_index=True, return_counts=True)
    avg = first + (counts - 1) / 2.0 + 1.0
    ranks[order] = np.repeat(avg, counts)
    u = ranks[: p.size].sum() - p.size * (p.size + 1) / 2.0
    return float(u / (p.size * q.size))


def relevance_auc(semantic_w: np.ndarray, relevance_w: np.ndarray, truth: TruthMaps, heads: Heads) -> float | None:
    if not heads.grounding_trained:
        return None
    seen = observed_cells(semantic_w)
    p_named = positive_probability(relevance_w, heads.grounding_w, heads.grounding_b)
    return auc(p_named[seen & truth.named], p_named[seen & ~truth.named])


def goal_mass(goal_w: np.ndarray, truth: TruthMaps, heads: Heads) -> float | None:
    if not heads.goal_trained:
        return None
    p_goal = positive_probability(goal_w, heads.goal_w, heads.goal_b).astype(np.float64)
    total = float(p_goal.sum())
    return float(p_goal[truth.region].sum() / total) if total > 0 else None


def agreement(semantic_w: np.ndarray, relevance_w: np.ndarray, goal_w: np.ndarray, truth: TruthMaps,
              heads: Heads) -> Agreement:
    """The three figures of one step's maps (channels first, as recorded)."""
    accuracy, cells = perception_accuracy(semantic_w, truth, heads)
    return Agreement(accuracy, relevance_auc(semantic_w, relevance_w, truth, heads),
                     goal_mass(goal_w, truth, heads), cells, float(truth.region.mean()))


def first_failures(figures: list[Agreement], thresholds: dict[str, float] | None = None,
                   heads: Heads | None = None) -> dict[str, int | None]:
    """For each figure, the first step from which it stayed at or below its threshold (`THRESHOLDS`: no better than
    chance) to the end of the episode, where that stage went wrong for good; None if it ended above it. Steps where
    a figure is undefined (nothing seen yet) count as wrong. (The first step at which a figure was low at all says
    little: every map is empty at the start.) With `heads`, the figures of heads the model never trained are left
    out: they are None throughout, which would read as wrong from the first step."""
    thresholds = thresholds or THRESHOLDS
    untrained = set() if heads is None else {name for name, trained in (
        ("perception", heads.perception_trained), ("relevance", heads.grounding_trained),
        ("goal", heads.goal_trained)) if not trained}
    out: dict[str, int | None] = {}
    for name, limit in thresholds.items():
        if name in untrained:
            continue
        def wrong(f: Agreement, name=name, limit=limit) -> bool:
            v = getattr(f, name)
            return v is None or v <= (limit * f.region_share if name == "goal" else limit)

        if not figures or not wrong(figures[-1]):
            out[name] = None
            continue
        t = len(figures)
        while t > 0 and wrong(figures[t - 1]):
            t -= 1
        out[name] = t
    return out
