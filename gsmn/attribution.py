"""Failure attribution from the model's own auxiliary heads (paper: Auxiliary Objectives, read backwards).

GSMN's auxiliary heads say what the model believes at each stage of its pipeline, so a failed episode can be
traced to the first stage that went wrong, using the maps the model held when the episode ended:

    perception  was the named landmark perceived: the perception head's most likely landmark at the cell of its
                centre (the cell J_percept is trained on) has the landmark's name; "never seen" when the camera
                never covered that cell;
    grounding   was it grounded: P(named landmark) from the grounding head is higher at its cell than at the
                cell of every other landmark of the world (landmarks sharing its name do not compete);
    goal        was the goal placed right: stopping at the peak of P(goal) from the goal head would have been a
                success (within the landmark region and in the quadrant asked);
    control     the goal map was right and the drone still ended elsewhere: it stopped away from the goal, or
                never stopped. Where the drone's final heading is known, the reason says which way: it stopped
                short (the peak ahead of it), overshot (behind it), or passed beside it (to its left or right).

A head trained without its objective (the ablations of Table 2: without J_percept, J_ground or J_plan) is its
initialisation, so its reading says nothing, and the stage it judges cannot be told apart from the next one: its
failures join the next judged stage's as one merged stage. Without J_percept a seen landmark's recognition is not
judged (a failure the grounding head finds is "perception_or_grounding"); without J_ground its grounding is not
(a misplaced goal is "grounding_or_goal"); without J_plan the goal is not (a grounded failure is
"goal_or_control"). "Never seen" needs no head and is always perception. Which heads were trained is read from the
model's own configuration (`trained_heads`).

The heads as arrays (`Heads`, `trained_heads`: gsmn.model.readout) and the map cells (`cell_of`, `cell_centre`,
`observed_cells`: gsmn.model.grid) are shared with the ground truth (gsmn.analysis.truth) and named here too.

`attribute` is a pure function of those maps, the head weights, the WorldSpec and the instruction; it is unit
tested on hand-made maps. `TraceRecorder` wraps a GSMN policy during evaluation to keep the final maps and a few
numbers per step, and `save_trace` / `load_trace` store them (compressed .npz, float16 maps, never unpickled).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from gsmn.analysis.truth import Agreement, agreement, first_failures, truth_maps
from gsmn.config import RunConfig
from gsmn.model.grid import cell_centre as cell_centre
from gsmn.model.grid import cell_of as cell_of
from gsmn.model.grid import observed_cells as observed_cells
from gsmn.model.heads import positive_probability, softmax
from gsmn.model.readout import Heads as Heads
from gsmn.model.readout import trained_heads as trained_heads
from gsmn.task.instructions import Instruction
from gsmn.task.metrics import side_of
from gsmn.world.catalogue import CATALOGUE
from gsmn.world.spec import WorldSpec, world_for_env

PIPELINE = ("perception", "grounding", "goal", "control")  # the stages in the order the model runs them
MERGED = ("perception_or_grounding", "grounding_or_goal", "goal_or_control")  # with one untrained head
STAGES = PIPELINE + MERGED
BEARINGS = ("ahead", "behind", "left", "right")  # 90-degree sectors around the drone's heading
STAGE_TITLES = {"perception": "not perceived", "grounding": "not grounded", "goal": "goal misplaced",
                "control": "control", "perception_or_grounding": "perception or grounding",
                "grounding_or_goal": "grounding or goal", "goal_or_control": "goal or control"}
STAGE_COLOURS = {"perception": "#8e44ad", "grounding": "#2870f5", "goal": "#e08020", "control": "#c0392b",
                 "perception_or_grounding": "#5b5fc7", "grounding_or_goal": "#a0694a",
                 "goal_or_control": "#d35400"}  # one colour per stage in the dashboard's bars and the figures


def reported_stages(*counts: dict[str, int]) -> tuple[str, ...]:
    """The stages to list for these counts: a merged stage only where some count has it (a model with an
    untrained head), so tables of GSMN failures keep their four rows."""
    extra = sorted({k for c in counts for k, n in c.items() if n and k not in STAGES})  # over two untrained heads
    return tuple(k for k in STAGES if k in PIPELINE or any(c.get(k, 0) for c in counts)) + tuple(extra)


@dataclass(frozen=True)
class FinalMaps:
    """The world-frame maps the model held at the last step of an episode, channels first, north-up."""

    semantic_map_w: np.ndarray  # (C_f, n, n)
    relevance_map_w: np.ndarray  # (3, n, n)
    goal_map_w: np.ndarray  # (2, n, n)


@dataclass(frozen=True)
class Attribution:
    """Where a failed episode went wrong (`stage`, one of STAGES; None for a success) and the evidence."""

    stage: str | None
    reason: str
    landmark_row: int  # the named landmark's centre cell
    landmark_col: int
    observed: bool  # the camera covered that cell at some step
    perceived: bool | None  # None: seen, but the model has no trained perception head to read it
    top_class: str | None  # the perception head's most likely landmark there (None: never observed)
    p_landmark_class: float  # the perception head's probability of the landmark's own class there
    landmark_class_rank: int  # 1 = most likely (ties share a rank)
    grounded: bool | None  # None: the model has no trained grounding head
    p_named: float  # P(named) at the landmark's cell
    p_named_other: float | None  # the highest P(named) at another landmark's cell (None: no other landmark)
    other_landmark: str | None  # ... and that landmark's name
    goal_right: bool | None  # None: the model has no trained goal head
    goal_peak_x: float  # the cell centre of the highest P(goal)
    goal_peak_y: float
    goal_peak_p: float
    goal_peak_error: float  # m from that peak to the true goal
    stopped: bool
    final_to_peak: float  # m from where the drone ended to the goal peak
    peak_bearing: str | None = None  # where that peak lay from the drone's final pose: BEARINGS; None: no heading
    # per stage (perception, grounding, goal): the step from which the map's agreement with the ground truth stayed
    # below its threshold to the end (gsmn.analysis.truth), None if it ended above it; None without per-step figures
    failed_from: dict[str, int | None] | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Attribution:
        return cls(**d)


# -- helpers ------------------------------------------------------------------------------------------------------
def bearing(from_xy: tuple[float, float], yaw: float, to_xy: tuple[float, float]) -> str:
    """Which of BEARINGS a point lies in as seen from a pose (x east, y north, yaw counter-clockwise from east):
    90-degree sectors centred on the heading ("ahead"), its opposite, and the two sides. The metric's quadrants
    (`side_of`) with the pose as the landmark and a start one metre behind it: "back" is ahead."""
    behind = (from_xy[0] - math.cos(yaw), from_xy[1] - math.sin(yaw))
    side = side_of(from_xy, behind, to_xy)
    return {"back": "ahead", "front": "behind"}.get(side, side)


_MISSED = {"ahead": "stopped {d:.1f} m short of it (the peak ahead)", "behind": "overshot it by {d:.1f} m (the peak "
           "behind)", "left": "stopped {d:.1f} m beside it (the peak to its left)",
           "right": "stopped {d:.1f} m beside it (the peak to its right)"}


def goal_peak(goal_map_w: np.ndarray, heads: Heads) -> tuple[int, int, float]:
    """(row, col, P(goal)) of the cell with the highest P(goal)."""
    p = positive_probability(goal_map_w, heads.goal_w, heads.goal_b)
    k = int(np.argmax(p))
    return k // p.shape[1], k % p.shape[1], float(p.flat[k])


_UNJUDGED = {  # what a merged stage's reason adds, per untrained head
    "perception": "Trained without J_percept, this model's perception head has no trained reading: a landmark not "
                  "recognised and one not grounded look alike.",
    "grounding": "Trained without J_ground, this model's grounding head has no trained reading: a landmark not "
                 "grounded and a misplaced goal look alike.",
    "goal": "Trained without J_plan, this model's goal map has no trained reading: a misplaced goal and poor control "
            "look alike."}


def merged_stage(stage: str, unjudged: tuple[str, ...]) -> str:
    """`stage` joined with the stages just before it that a model's untrained heads cannot judge ("control" after
    an unjudged "goal" -> "goal_or_control")."""
    parts = [stage]
    for previous in reversed(PIPELINE[:PIPELINE.index(stage)]):
        if previous not in unjudged:
            break
        parts.insert(0, previous)
    return "_or_".join(parts)


# -- the attribution ----------------------------------------------------------------------------------------------
def attribute(maps: FinalMaps, heads: Heads, world: WorldSpec, instruction: Instruction,
              final_xy: tuple[float, float], stopped: bool, success: bool, success_radius: float = 6.0,
              final_yaw: float | None = None) -> Attribution:
    """Attribute an episode's outcome to the first stage of the pipeline the model got wrong (see the module
    docstring). `success` is the episode's own metric; for a success the stage is None and the evidence is
    still filled in. `final_yaw` (radians), where known, says which way a control failure missed the peak."""
    F = world.field_size
    n = maps.semantic_map_w.shape[-1]
    target = world.landmarks[instruction.landmark_index]
    r, c = cell_of(target.x, target.y, F, n)

    # perception at the landmark's cell
    feature = maps.semantic_map_w[:, r, c].astype(np.float32)
    observed = bool(np.abs(feature).max() > 1e-6)
    probs = softmax(np.einsum("kc,c->k", heads.perception_w.astype(np.float32), feature)
                    + heads.perception_b.astype(np.float32))
    order = np.argsort(-probs, kind="stable")
    rank = 1 + int((probs > probs[target.class_id]).sum())  # ties share a rank
    top = CATALOGUE[int(order[0])].noun_phrase if observed else None
    perceived = observed and top == target.noun_phrase  # models sharing a name (4 palm trees) count as right
    if observed and not heads.perception_trained:
        perceived = None  # no trained reading: the next stage's verdict covers it

    # grounding: P(named) at its cell against every other landmark's cell
    p_named_map = positive_probability(maps.relevance_map_w, heads.grounding_w, heads.grounding_b)
    p_named = float(p_named_map[r, c])
    others = [(float(p_named_map[cell_of(lm.x, lm.y, F, n)]), lm.noun_phrase) for lm in world.landmarks
              if lm.noun_phrase != target.noun_phrase]
    best_other = max(others, default=None)
    grounded = p_named > (best_other[0] if best_other else 0.5) if heads.grounding_trained else None

    # goal: would stopping at the peak of P(goal) have succeeded?
    gr, gc, gp = goal_peak(maps.goal_map_w, heads)
    gx, gy = cell_centre(gr, gc, F, n)
    start = (world.start_x, world.start_y)
    goal_right = None  # no trained goal head (no J_plan): its peak says nothing
    if heads.goal_trained:
        goal_right = math.dist((gx, gy), (target.x, target.y)) < success_radius and \
            side_of((target.x, target.y), start, (gx, gy)) == instruction.side
    final_to_peak = math.dist(final_xy, (gx, gy))
    peak_bearing = None if final_yaw is None else bearing(final_xy, final_yaw, (gx, gy))

    name = target.noun_phrase
    unjudged = tuple(stage for stage, verdict in (("perception", perceived), ("grounding", grounded),
                                                  ("goal", goal_right)) if verdict is None)
    seen = "Perceived" if perceived else "Seen"  # as far as the trained heads can tell
    so_far = "Grounded" if grounded else seen
    if success:
        stage, reason = None, "Success."
    elif not observed:
        stage, reason = "perception", f"The camera never covered the {name}'s cell: it was never seen."
    elif perceived is False:
        stage, reason = "perception", (f"Seen but not recognised: the perception head reads the {name}'s cell as "
                                       f"{top} (the {name} ranks {rank}, p {probs[target.class_id]:.2f}).")
    elif grounded is False:
        against = f"{best_other[0]:.2f} at the {best_other[1]}" if best_other else "under 0.5"
        stage, reason = "grounding", f"{seen} but not grounded: P(named) {p_named:.2f} at the {name}, {against}."
    elif goal_right is False:
        stage, reason = "goal", (f"{so_far}, but the goal map peaks {math.dist((gx, gy), instruction.goal):.1f} m "
                                 f"from the true goal, where stopping would fail.")
    elif goal_right is None:
        how = "stopped" if stopped else "never said STOP, and ended"
        stage, reason = "control", f"{so_far}, but the drone {how} {math.dist(final_xy, instruction.goal):.1f} m " \
                                   f"from the goal."
    else:
        if not stopped:
            how = "never said STOP"
        elif peak_bearing is None:
            how = f"stopped {final_to_peak:.1f} m from it"
        else:
            how = _MISSED[peak_bearing].format(d=final_to_peak)
        stage, reason = "control", f"The goal map was right, but the drone {how}."
    if stage is not None:  # a failure an untrained head may hide is also the stages before it that it cannot judge
        stage = merged_stage(stage, unjudged)
        reason += "".join(f" {_UNJUDGED[s]}" for s in stage.split("_or_") if s in unjudged)
    return Attribution(
        stage=stage, reason=reason, landmark_row=r, landmark_col=c, observed=observed, perceived=perceived,
        top_class=top, p_landmark_class=float(probs[target.class_id]), landmark_class_rank=rank, grounded=grounded,
        p_named=p_named, p_named_other=best_other[0] if best_other else None,
        other_landmark=best_other[1] if best_other else None, goal_right=goal_right, goal_peak_x=gx, goal_peak_y=gy,
        goal_peak_p=gp, goal_peak_error=math.dist((gx, gy), instruction.goal), stopped=stopped,
        final_to_peak=final_to_peak, peak_bearing=peak_bearing)


def attribute_record(record: dict, trace: ModelTrace, heads: Heads, config: RunConfig) -> Attribution:
    """`attribute` for one episode of a `gsmn eval` result (a dict as in its JSON) and its recorded trace, under
    the evaluation's RunConfig (the world is rebuilt from the episode's env id)."""
    world = world_for_env(int(record["env_id"]), config.world)
    instruction = Instruction(text=record["instruction"], landmark_index=int(record["landmark_index"]),
                              noun_phrase=record["noun_phrase"], side=record["side"],
                              goal_x=float(record["goal_x"]), goal_y=float(record["goal_y"]),
                              ambiguous=bool(record["ambiguous"]))
    final_yaw = record.get("final_yaw")  # progress lines (the dashboard's) carry it instead of the trajectory
    if final_yaw is None and record.get("trajectory"):
        final_yaw = record["trajectory"][-1][3]
    a = attribute(trace.maps, heads, world, instruction, (float(record["final_x"]), float(record["final_y"])),
                  bool(record["stopped"]), bool(record["success"]), config.task.success_radius,
                  None if final_yaw is None else float(final_yaw))
    return replace(a, failed_from=failed_from(trace.truth, heads))


def count_stages(attributions: list[Attribution | None]) -> dict[str, int]:
    """How many failures each stage explains (successes and episodes without maps are not counted)."""
    counts = dict.fromkeys(STAGES, 0)
    for a in attributions:
        if a is not None and a.stage is not None:
            counts[a.stage] = counts.get(a.stage, 0) + 1  # a stage merged over two untrained heads is not in STAGES
    return counts


# -- recording during evaluation ------------------------------------------------------------------------------
@dataclass(frozen=True)
class ModelTrace:
    """What attribution and the failure browser need from one episode of a GSMN: the final maps, and per step
    the model's own action, P(stop), P(named) at the named landmark's cell and the goal peak."""

    maps: FinalMaps
    v: np.ndarray  # (T,) m/s, the model's own action
    omega: np.ndarray  # (T,) rad/s
    stop_probability: np.ndarray  # (T,)
    p_named: np.ndarray  # (T,) P(named) at the named landmark's cell
    goal_peak_rc: np.ndarray  # (T, 2) int, the cell of the highest P(goal)
    goal_peak_p: np.ndarray  # (T,)
    # (T, 4) the maps' agreement with the ground truth per step: perception, relevance, goal (NaN: undefined) and
    # the success region's share of the field (gsmn.analysis.truth); None in traces written before it
    truth: np.ndarray | None = None


FIGURE_STAGES = {"perception": "perception", "relevance": "grounding", "goal": "goal"}


def failed_from(truth: np.ndarray | None, heads: Heads | None = None) -> dict[str, int | None] | None:
    """The step each stage went wrong for good, from a trace's per-step figures, by stage name; without the stages
    whose head `heads` says was not trained."""
    if truth is None or len(truth) == 0:
        return None
    def value(x) -> float | None:
        return None if not np.isfinite(x) else float(x)

    figures = [Agreement(value(p), value(r), value(g), 0, float(share))
               for p, r, g, share in np.asarray(truth, np.float64)]
    return {FIGURE_STAGES[k]: v for k, v in first_failures(figures, heads=heads).items()}


class TraceRecorder:
    """A GSMN policy that keeps a ModelTrace of its episode (evaluation wraps the policy in one)."""

    def __init__(self, policy):
        self.policy = policy
        self.name, self.needs_images = policy.name, policy.needs_images
        self.heads = Heads.of(policy.model)
        self._rows: list[tuple] = []
        self._cell = (0, 0)
        self._last = None

    def reset(self, task) -> None:
        self.policy.reset(task)
        lm = task.world.landmarks[task.instruction.landmark_index]
        self._cell = cell_of(lm.x, lm.y, task.world.field_size, self.policy.model.config.model.map_size)
        self._rows, self._last, self._figures = [], None, []
        self._truth = truth_maps(task.world, task.instruction, self.policy.model.config.model.map_size,
                                 self.policy.config.task.success_radius)

    def act(self, obs):
        action = self.policy.act(obs)
        out = self.policy.last_outputs
        relevance = out.relevance_map_w[0, 0].float().numpy()
        goal = out.goal_map_w[0, 0].float().numpy()
        r, c = self._cell
        p_named = positive_probability(relevance[:, r:r + 1, c:c + 1], self.heads.grounding_w,
                                       self.heads.grounding_b)[0, 0]
        gr, gc, gp = goal_peak(goal, self.heads)
        drone = self.policy.config.drone
        self._rows.append((float(out.v[0, 0]) * drone.max_forward_velocity,
                           float(out.omega[0, 0]) * drone.max_yaw_rate,
                           float(torch.sigmoid(out.stop_logit[0, 0])), float(p_named), gr, gc, gp))
        self._last = out
        f = agreement(out.semantic_map_w[0, 0].float().numpy(), relevance, goal, self._truth, self.heads)
        self._figures.append((*(np.nan if v is None else v for v in (f.perception, f.relevance, f.goal)),
                              f.region_share))
        return action

    def trace(self) -> ModelTrace:
        if self._last is None:
            raise RuntimeError("no step recorded: fly an episode first")
        out = self._last
        maps = FinalMaps(*(t[0, 0].to(torch.float16).numpy().copy()
                           for t in (out.semantic_map_w, out.relevance_map_w, out.goal_map_w)))
        a = np.array([row[:4] + (row[6],) for row in self._rows], np.float32)
        rc = np.array([row[4:6] for row in self._rows], np.int16)
        return ModelTrace(maps, v=a[:, 0], omega=a[:, 1], stop_probability=a[:, 2], p_named=a[:, 3],
                          goal_peak_rc=rc, goal_peak_p=a[:, 4], truth=np.array(self._figures, np.float32))


def save_trace(path: Path | str, trace: ModelTrace) -> None:
    """Write atomically (a temporary file renamed into place)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.npz")
    m = trace.maps
    np.savez_compressed(tmp, semantic_map_w=m.semantic_map_w.astype(np.float16),
                        relevance_map_w=m.relevance_map_w.astype(np.float16),
                        goal_map_w=m.goal_map_w.astype(np.float16), v=trace.v, omega=trace.omega,
                        stop_probability=trace.stop_probability, p_named=trace.p_named,
                        goal_peak_rc=trace.goal_peak_rc, goal_peak_p=trace.goal_peak_p,
                        **({} if trace.truth is None else {"truth": trace.truth}))
    tmp.replace(path)


def load_trace(path: Path | str) -> ModelTrace:
    with np.load(path, allow_pickle=False) as f:
        d = {k: f[k] for k in f.files}
    maps = FinalMaps(d.pop("semantic_map_w"), d.pop("relevance_map_w"), d.pop("goal_map_w"))
    return ModelTrace(maps, **d)


def trace_path(folder: Path | str, env_id: int) -> Path:
    return Path(folder) / f"env_{env_id:06d}.npz"
