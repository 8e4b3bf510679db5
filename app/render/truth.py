"""Ground truth under the model's maps, as the dashboard shows and serves it (`gsmn.analysis.truth` computes it).

Three layers, in the colours of the model map each is read against, so the two can be compared cell by cell:

- truth_semantic: the true landmark of every cell (the footprints), in the semantic map's class palette; cells
  outside every footprint in the colour the semantic map gives unseen cells, darker;
- truth_relevance: the named landmark's footprint, viridis 1 (yellow) on 0 (purple), as P(named) in its fixed range;
- truth_goal: the success region, viridis 1 on 0 as P(goal), the goal's own cell in red.

And the agreement figures of every recorded step (perception, relevance AUC, goal mass), computed once per step and
kept with the episode's id (episodes only grow, so a live episode's new steps are added as they are asked for).
"""

from __future__ import annotations

import threading

import numpy as np

from app.live.models import MapHeads
from app.live.recording import FINISHED, Episode
from app.render.colors import UNSEEN_RGB, apply_colormap
from app.render.layers import palette_of
from gsmn.analysis.truth import Agreement, TruthMaps, agreement, first_failures, truth_maps

TRUTH_LAYERS = ("truth_semantic", "truth_relevance", "truth_goal")
TRUTH_TITLES = {"truth_semantic": "Truth: the landmark at each cell", "truth_relevance": "Truth: the named landmark",
                "truth_goal": "Truth: the success region and the goal"}
GOAL_RGB = (230, 40, 40)
_lock = threading.Lock()
_truth: dict[tuple, TruthMaps] = {}
_figures: dict[int, tuple[int, list[Agreement | None]]] = {}  # episode id -> (its step count when computed, figures)
MAX_KEPT = 256


def episode_truth(episode: Episode, n: int, success_radius: float = 6.0) -> TruthMaps:
    world, instruction = episode.task.world, episode.task.instruction
    key = (world.env_id, instruction.text, n, success_radius)
    with _lock:
        found = _truth.get(key)
    if found is None:
        found = truth_maps(world, instruction, n, success_radius)
        with _lock:
            if len(_truth) >= MAX_KEPT:
                _truth.clear()
            _truth[key] = found
    return found


def truth_rgb(layer: str, truth: TruthMaps, heads: MapHeads) -> np.ndarray:
    """(n, n, 3) uint8, north-up, one pixel per cell."""
    if layer == "truth_semantic":
        palette = palette_of(heads)
        rgb = np.empty((*truth.class_id.shape, 3), np.uint8)
        rgb[:] = np.array(UNSEEN_RGB, np.float32) * 0.6
        inside = truth.class_id >= 0
        rgb[inside] = palette[truth.class_id[inside]]
        return rgb
    if layer == "truth_relevance":
        return apply_colormap(truth.named.astype(np.float32), 0.0, 1.0)
    if layer == "truth_goal":
        rgb = apply_colormap(truth.region.astype(np.float32), 0.0, 1.0)
        rgb[truth.goal_cell] = GOAL_RGB
        return rgb
    raise ValueError(f"unknown truth layer {layer!r}; choose from {', '.join(TRUTH_LAYERS)}")


def step_figures(episode: Episode, heads: MapHeads, success_radius: float = 6.0) -> list[Agreement | None]:
    """The agreement figures of every recorded step (None where no model watched the step)."""
    steps = list(episode.steps)
    with _lock:
        count, figures = _figures.get(episode.id, (0, []))
        figures = list(figures)
    if count > len(steps):  # not this episode (ids are not reused), but be safe
        count, figures = 0, []
    truth = None
    for s in steps[count:]:
        if s.maps is None:
            figures.append(None)
            continue
        if truth is None:
            truth = episode_truth(episode, s.maps.semantic_w.shape[-1], success_radius)
        figures.append(agreement(s.maps.semantic_w, s.maps.relevance_w, s.maps.goal_w, truth, heads))
    with _lock:
        if len(_figures) >= MAX_KEPT:
            _figures.clear()
        _figures[episode.id] = (len(steps), figures)
    return figures


def went_wrong(figures: list[Agreement | None], heads: MapHeads | None = None) -> dict[str, int | None] | None:
    """The step at which each figure fell below its threshold for good (`gsmn.analysis.truth.first_failures`),
    without the figures of heads the model never trained (`heads`; their figures are None throughout, which
    `first_failures` would read as wrong from the first step)."""
    known = [f for f in figures if f is not None]
    if not known:
        return None
    steps = first_failures(known, heads=heads)
    if heads is None and all(f.goal is None for f in known):  # heads unknown: a goal never measured says nothing
        del steps["goal"]
    return steps


STAGE_OF_FIGURE = {"perception": "perception", "relevance": "grounding", "goal": "goal"}
# The truth figures read whole maps (every seen landmark cell, the relevance over the field, the goal mass), where the
# attribution reads the named landmark and the goal: so their words differ, and "right" or "wrong" is said of neither.
FIGURE_WORDS = {"perception": "landmarks read", "grounding": "relevance", "goal": "goal mass"}
TRUTH_ROW = "whole maps vs truth"


def went_wrong_text(steps: dict[str, int | None] | None, bold: tuple[str, str] = ("**", "**")) -> str:
    """"landmarks read: above chance to the end · relevance: at chance from step 23 · goal mass: at chance from step
    41", keyed by stage (`Attribution.failed_from`) or by figure (`went_wrong`): from which step each whole-map figure
    stayed no better than chance (`gsmn.analysis.truth.first_failures`)."""
    if not steps:
        return ""
    if all(step is None for step in steps.values()):
        return "every figure above chance to the end"
    parts = []
    for key, step in steps.items():
        stage = STAGE_OF_FIGURE.get(key, key)
        words = FIGURE_WORDS.get(stage, stage)
        parts.append(f"{words}: above chance to the end" if step is None else
                     f"{words}: at chance from step {bold[0]}{step}{bold[1]}")
    return " · ".join(parts)


def result_rows(episode: Episode, heads: MapHeads | None, success_radius: float = 6.0) -> str:
    """Rows for the result table: the maps' agreement with the ground truth at the end and from which step each
    went wrong for good ("" without model maps)."""
    if heads is None or not episode.steps or episode.steps[-1].maps is None:
        return ""
    figures = step_figures(episode, heads, success_radius)
    last = figures[-1]
    if last is None:
        return ""

    def fmt(x: float | None) -> str:
        return "n/a" if x is None else f"{x:.2f}"

    # an episode stopped early has no result table above these rows (app.render.panels.result_markdown): their own
    header = "\n| | |\n|---|---|\n" if episode.result is None or episode.status != FINISHED else ""
    return (f"{header}| truth at the end | perception {fmt(last.perception)}, relevance AUC {fmt(last.relevance)}, "
            f"goal mass {fmt(last.goal)} |\n| {TRUTH_ROW} | {went_wrong_text(went_wrong(figures, heads))} |\n")
