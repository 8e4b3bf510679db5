"""The model's maps as layers a person can read (paper: Model Architecture; docs/model.md for the maps).

- semantic: the perception head (semantic-map cell -> 63 landmark classes) on every cell, read one of two ways
  (`SEMANTIC_READINGS`). "all": the most likely of all 63 classes, drawn in this world's landmark colours with a
  legend (one entry per name), pale where the head reads a landmark this world does not have (it has no "open
  ground" class, so open ground reads as any of them: a mosaic). "world": the most likely of this world's
  landmarks or "nothing" (the rest of the classes together), pale for nothing, with every one of this world's
  landmarks in the legend; presenter mode and the exports read it so. Grey where the camera has not looked yet.
- relevance: P(the cell holds the landmark the instruction names), the grounding head Linear(3 -> 2) on the
  relevance map; cells never observed are left transparent on the ground.
- goal: P(the cell is the goal), the goal head Linear(2 -> 2) on the world-frame goal map.
- goal_robot: the same on the robot-frame goal map the controller reads (drone at the centre, facing up).
  A model trained without J_plan has no trained goal head; its goal layers show channel 0 in both modes. Likewise
  without J_percept the semantic layer shows the semantic map's 32 channels reduced to their three principal
  components over the seen cells, as red, green and blue (an untrained head's reading says nothing;
  `gsmn.attribution.trained_heads`). Without J_ground the relevance layer shows the relevance map's three channels
  at once, as red, green and blue: no single channel need carry the grounding (a model trained so puts the named
  landmark in whichever channel its goal filters read it from; docs/results.md, Figure 5). A model without a
  grounding or goal filter (the original code's module ablations, docs/model.md) says so in that layer's title, and
  shows what its next stage reads in the map's place: the semantic map's first channels.

The heads are the auxiliary classifiers trained with the model (gsmn/model/heads.py), so these are the
model's own readings of its maps. "raw" shows channel 0 of the relevance and goal maps instead.

The layers are listed from the model's output record (`GSMNOutputs.maps()`, the fields named `<content>_map_<frame>`
and the like): the four above are its maps the heads read; any other map the record holds (the coverage, the
robot-frame relevance map, a map added to the record later) is a layer too, showing its channel 0.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from app.live.flight import NOT_KEPT
from app.live.models import MapHeads
from app.render.colors import (
    apply_colormap,
    channels_legend_html,
    channels_rgb,
    class_palette,
    colorbar_html,
    name_palette,
    principal_components,
    semantic_classes,
    semantic_legend_html,
    semantic_rgb,
    world_classes,
    world_legend_html,
    world_reading,
)
from gsmn.attribution import cell_centre
from gsmn.model.grid import world_cell
from gsmn.model.gsmn import GSMNOutputs
from gsmn.model.heads import positive_probability, softmax
from gsmn.world.landmarks import CATALOGUE

# the record's maps the heads read, and the names of their layers (in the page and the API)
READ_MAPS = {"semantic_map_w": "semantic", "relevance_map_w": "relevance", "goal_map_w": "goal",
             "goal_map_r": "goal_robot"}
RECORD_MAPS = tuple(f.name for f in fields(GSMNOutputs) if f.name[-2:] in ("_c", "_w", "_r"))  # as .maps() names
LAYERS = (*READ_MAPS.values(), *(m for m in RECORD_MAPS if m not in READ_MAPS and m not in NOT_KEPT))
TITLES = {"semantic": "Semantic map: most likely landmark", "semantic_world": "Semantic map: which of this world's "
          "landmarks, or nothing", "relevance": "Relevance: P(named landmark)",
          "goal": "Goal: P(goal)", "goal_robot": "Goal, drone's frame (steers it)"}
FRAMES = {"_w": "world", "_r": "robot", "_c": "camera"}
VALUE_MODES = ("probability", "raw")
RANGE_MODES = ("fixed", "frame")
SEMANTIC_READINGS = ("all", "world")  # the semantic map over all 63 classes, or this world's landmarks and nothing
NOTHING_ALPHA = 0.3  # on the ground, a cell read "nothing" lets the field show through (landmarks stand out)
NO_GOAL_HEAD = "channel 0 (no J_plan)"
NO_GROUNDING_HEAD = "each scaled to its range over seen cells (no J_ground, so no P(named))"
NO_PERCEPTION_HEAD = ("principal components over this frame's seen cells, on one scale; like colours, like "
                      "features (no J_percept, so no landmark classes)")


_PALETTE = class_palette(len(CATALOGUE))


def palette_of(heads: MapHeads) -> np.ndarray:
    """One colour per class the perception head reads (`heads.class_names`)."""
    return _PALETTE[: len(heads.class_names)]


@dataclass(frozen=True)
class Layer:
    name: str
    title: str
    rgb: np.ndarray  # (H, W, 3) uint8, one pixel per cell, north-up (robot frame: facing up)
    alpha: np.ndarray  # (H, W) float in [0, 1]: how opaque each cell is on the ground (low values show the field)
    legend_html: str
    values: np.ndarray | None = None  # (H, W) the scalar shown, for inspection (None: several channels at once)
    frame: str = "world"  # "world" (north up, can lie on the ground), "robot" (ahead up) or "camera"


def frame_of(map_name: str) -> str:
    return FRAMES.get(map_name[-2:], "world")


def map_title(map_name: str) -> str:
    """A title for a map the heads do not read, from its name: 'relevance_map_r' -> 'Relevance map, robot frame'."""
    words = map_name[:-2].replace("_", " ") if map_name[-2:] in FRAMES else map_name.replace("_", " ")
    return f"{words[:1].upper()}{words[1:]}, {frame_of(map_name)} frame"


def _scalar_layer(name: str, values: np.ndarray, alpha: np.ndarray, range_mode: str, label: str,
                  title: str | None = None, frame: str = "world") -> Layer:
    if range_mode == "fixed" and label.startswith("P("):
        vmin, vmax = 0.0, 1.0
    else:
        vmin, vmax = float(np.min(values)), float(np.max(values))
        if vmax - vmin < 1e-6:
            vmax = vmin + 1e-6
    legend = colorbar_html(vmin, vmax, "viridis", label + (" (this frame's range)" if range_mode == "frame" else ""))
    # On the ground a scalar map is a heat overlay: opacity grows with the value, so the field and the
    # landmarks show through where the map is low.
    heat = 0.12 + 0.88 * np.clip((values - vmin) / (vmax - vmin), 0.0, 1.0)
    return Layer(name, title or TITLES[name], apply_colormap(values, vmin, vmax), alpha * heat, legend, values, frame)


def _channels_layer(name: str, maps: np.ndarray, observed: np.ndarray, label: str, title: str,
                    channel: str = "channel", start: int = 0, shared: bool = False) -> Layer:
    """Up to three channels of a map as one picture (`app.render.colors.channels_rgb`), for a map no trained head reads;
    opacity grows with the brightest channel, as `_scalar_layer`'s does with its value."""
    rgb, brightest = channels_rgb(maps, observed, shared)
    return Layer(name, title, rgb, observed.astype(np.float32) * (0.12 + 0.88 * brightest),
                 channels_legend_html(label, min(3, len(maps)), channel, start))


def _semantic_layer(semantic_w: np.ndarray, heads: MapHeads, world_names: tuple[str, ...] | None,
                    reading: str = "all") -> tuple[Layer, np.ndarray]:
    """The semantic layer read over all classes or this world's (`SEMANTIC_READINGS`; "world" needs
    `world_names`), and which cells the camera has seen."""
    if heads.perception_trained and reading == "world" and world_names:
        names = sorted(set(world_names))
        index, p, observed = world_reading(semantic_w, heads.perception_w, heads.perception_b, heads.class_names,
                                           names)
        palette = name_palette(heads.class_names, names)
        alpha = observed * np.where(index < 0, NOTHING_ALPHA, 1.0).astype(np.float32)  # the field shows through
        return Layer("semantic", TITLES["semantic_world"], semantic_rgb(index, p, observed, palette, len(names) + 1),
                     alpha, world_legend_html(index, observed, palette, names), p), observed
    classes, confidence, observed = semantic_classes(semantic_w, heads.perception_w, heads.perception_b)
    if world_names:
        names = sorted(set(world_names))
        classes = world_classes(classes, heads.class_names, names)
        palette = name_palette(heads.class_names, names)
    else:
        names, palette = list(heads.class_names), palette_of(heads)
    if heads.perception_trained:
        semantic = Layer("semantic", TITLES["semantic"],
                         semantic_rgb(classes, confidence, observed, palette, len(heads.class_names)),
                         observed.astype(np.float32), semantic_legend_html(classes, observed, palette, names),
                         confidence)
    else:  # no J_percept: the head's classes say nothing; show the map itself, its features reduced to three
        semantic = _channels_layer("semantic", principal_components(semantic_w, observed), observed,
                                   NO_PERCEPTION_HEAD, "Semantic map: its features' 3 main components as red, green, "
                                   "blue (no perception head, no J_percept)", "component", 1, shared=True)
    return semantic, observed


def build_layers(semantic_w: np.ndarray, relevance_w: np.ndarray, goal_w: np.ndarray, goal_r: np.ndarray,
                 heads: MapHeads, value_mode: str = "probability", range_mode: str = "fixed",
                 world_names: tuple[str, ...] | None = None, semantic_reading: str = "all") -> dict[str, Layer]:
    """All four layers of one step (maps as stored: float16 or float32, channels first). With `world_names` (the
    world's landmark names) the semantic map colours and lists only those, one entry per name, and draws cells
    read as another world's landmark in one pale colour (`app.render.colors.world_classes`); with
    `semantic_reading` "world" too, it reads each cell as one of them or nothing (`app.render.colors.world_reading`)."""
    if value_mode not in VALUE_MODES:
        raise ValueError(f"value_mode must be one of {VALUE_MODES}, got {value_mode!r}")
    if range_mode not in RANGE_MODES:
        raise ValueError(f"range_mode must be one of {RANGE_MODES}, got {range_mode!r}")
    if semantic_reading not in SEMANTIC_READINGS:
        raise ValueError(f"semantic_reading must be one of {SEMANTIC_READINGS}, got {semantic_reading!r}")
    semantic, observed = _semantic_layer(semantic_w, heads, world_names, semantic_reading)
    relevance_title = goal_title = None
    if value_mode == "probability":
        if heads.grounding_trained:
            relevance, relevance_label = positive_probability(relevance_w, heads.grounding_w, heads.grounding_b), \
                "P(named)"
        else:  # no J_ground: show all of what the goal filters read
            relevance, relevance_label = None, NO_GROUNDING_HEAD
            relevance_title = "Relevance: channels 0, 1, 2 as red, green, blue (no grounding head, no J_ground)"
            if not heads.grounding_filter:  # nothing grounds the instruction: say so, and what stands in its place
                relevance_title = ("No relevance map: this model has no grounding filter (as the original code's "
                                   "-J_ground). Shown: semantic channels 0, 1, 2 as red, green, blue, what its goal "
                                   "filter reads")
        if heads.goal_trained:
            goal = positive_probability(goal_w, heads.goal_w, heads.goal_b)
            goal_robot = positive_probability(goal_r, heads.goal_w, heads.goal_b)
            labels = (relevance_label, "P(goal)", "P(goal)")
        else:  # no J_plan: show what the controller reads
            goal, goal_robot = (np.asarray(m[0], np.float32) for m in (goal_w, goal_r))
            labels = (relevance_label, NO_GOAL_HEAD, NO_GOAL_HEAD)
            goal_title = "Goal: channel 0 (no goal head, no J_plan)"
            if not heads.goal_filter:
                first = 0 if heads.grounding_filter else 3  # the stack's channels after R (gsmn.model.gsmn)
                goal_title = (f"No goal map: this model has no goal filter (as the original code's -J_goal). Shown: "
                              f"semantic channel {first}, which its controller reads in the goal map's place")
    else:
        relevance, goal, goal_robot = (np.asarray(m[0], np.float32) for m in (relevance_w, goal_w, goal_r))
        labels = ("relevance channel 0", "goal channel 0", "goal channel 0")
    ones = np.ones(goal.shape, np.float32)
    out = {"semantic": semantic,
           "relevance": _scalar_layer("relevance", relevance, observed.astype(np.float32), range_mode, labels[0],
                                      relevance_title) if relevance is not None else
           _channels_layer("relevance", np.asarray(relevance_w, np.float32), observed, labels[0], relevance_title),
           "goal": _scalar_layer("goal", goal, ones, range_mode, labels[1], goal_title),
           "goal_robot": _scalar_layer("goal_robot", goal_robot, np.ones(goal_robot.shape, np.float32), range_mode,
                                       labels[2], frame="robot")}
    mark_drone(out["goal_robot"].rgb)
    return out


def map_layers(maps: dict[str, np.ndarray], heads: MapHeads, value_mode: str = "probability",
               range_mode: str = "fixed", world_names: tuple[str, ...] | None = None,
               semantic_reading: str = "all") -> dict[str, Layer]:
    """A layer for each map of one step of the output record (`GSMNOutputs.maps()` names, channels first): the maps
    the heads read as `build_layers` shows them, then every other one as its channel 0 (this frame's range)."""
    out = build_layers(*(maps[name] for name in READ_MAPS), heads, value_mode, range_mode, world_names,
                       semantic_reading)
    for name, m in maps.items():
        if name in READ_MAPS:
            continue
        values = np.asarray(m[0] if m.ndim == 3 else m, np.float32)  # (H, W)
        frame = frame_of(name)
        out[name] = _scalar_layer(name, values, np.ones(values.shape, np.float32), "frame", "channel 0",
                                  map_title(name), frame)
        if frame == "robot":
            mark_drone(out[name].rgb)
    return out


def mark_drone(rgb: np.ndarray) -> None:
    """Draw the drone at the centre of a robot-frame map (the corner of the four middle cells), in place: a white
    2x2 block with a black cell ahead of it, so the heading (up) reads at a glance."""
    h, w = rgb.shape[:2]
    r, c = h // 2, w // 2
    rgb[r - 1:r + 1, c - 1:c + 1] = 255
    rgb[r - 3:r - 1, c - 1:c + 1] = (255, 255, 255)
    rgb[r - 4, c - 1:c + 1] = 0


@dataclass(frozen=True)
class CellReport:
    """What the model holds at one world-map cell, beside the ground truth there."""

    row: int
    col: int
    x: float  # the cell's centre (m)
    y: float
    observed: bool
    classes: tuple[tuple[str, float], ...]  # the perception head's three most likely landmarks (none: untrained)
    p_named: float  # nan: the model has no trained grounding head
    p_goal: float  # nan: the model has no trained goal head
    truth: str | None  # the landmark whose radius covers the cell centre, if any
    relevance: tuple[float, ...] = ()  # the relevance map's channels at the cell (what the grounding head reads)


def inspect_cell(x: float, y: float, semantic_w: np.ndarray, relevance_w: np.ndarray, goal_w: np.ndarray,
                 heads: MapHeads, world) -> CellReport | None:
    """The cell under the world point (x, y); None outside the map."""
    C, n, _ = semantic_w.shape
    r, c = world_cell(x, y, world.field_size, n)
    if not (0 <= r < n and 0 <= c < n):
        return None
    feature = semantic_w[:, r, c].astype(np.float32)
    probs = softmax(np.einsum("kc,c->k", heads.perception_w, feature) + heads.perception_b)
    # a class with several models ("bush", "tower") once, at its likeliest model's probability: the reading the
    # failure attribution gives (gsmn.attribution: the head's argmax, models sharing a name counting as one)
    by_name: dict[str, float] = {}
    for name, p in zip(heads.class_names, probs.tolist(), strict=True):
        by_name[name] = max(by_name.get(name, 0.0), p)
    top = sorted(by_name.items(), key=lambda kv: -kv[1])[:3]
    cx, cy = cell_centre(r, c, world.field_size, n)
    truth = next((lm.noun_phrase for lm in world.landmarks if np.hypot(lm.x - cx, lm.y - cy) <= lm.radius), None)
    p_named = positive_probability(relevance_w[:, r:r + 1, c:c + 1], heads.grounding_w, heads.grounding_b)[0, 0] \
        if heads.grounding_trained else float("nan")
    p_goal = positive_probability(goal_w[:, r:r + 1, c:c + 1], heads.goal_w, heads.goal_b)[0, 0] \
        if heads.goal_trained else float("nan")
    return CellReport(r, c, cx, cy, bool(np.abs(feature).max() > 1e-6),
                      tuple(top) if heads.perception_trained else (),
                      float(p_named), float(p_goal),
                      truth, tuple(float(v) for v in relevance_w[:, r, c]))
