"""Map interventions: from a step on, the model flies with a corrected map in place of its own (docs/model.md,
"Interventions").

Which map: the semantic map ("perfect perception"), the relevance map ("perfect grounding") or the goal map
("perfect goal"); with what: the ground truth, or the model's own map with painted edits (a peak added, a blob
erased: relevance and goal maps only). The substitute is written in the model's own coding, `MapCodes`, read off
the model's own maps on cells of each kind over calibration flights on dev environments (`derive_codes`):

- semantic map (C_f channels): per landmark class, the mean feature vector over the seen footprint cells of that
  class; the background, the mean over seen cells outside every footprint. A class never seen in calibration takes
  the background moved along the perception head's direction for that class, as far as the seen classes lie from it.
- relevance map (3 channels): the mean over the named landmark's seen footprint cells, over the other landmarks'
  footprint cells, and over the seen background, in episodes the model flew to success (its maps were right).
- goal map (2 channels): the mean map around the true goal cell, offset by offset, in a (2r+1)^2 window (the shape
  of a goal peak, not a single cell), and the mean beyond it, in episodes flown to success.

A truth map covers the whole field, as if every cell had been seen. `hold` (the default) puts the substitute in
place of the model's map at every step from the intervention on; `hold=False` writes it once into the semantic map
the model keeps integrating, so what the camera sees afterwards fades it (the leaky integrator). Only the semantic
map is integrated: the relevance and goal maps are made afresh from it at every step, so they can only be held.
Holding is the default because it answers the attribution's question cleanly ("had this stage been right, would
the episode have succeeded?"); writing once asks a different one (would the model keep a right map?).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from gsmn.analysis.truth import TruthMaps, truth_maps
from gsmn.model.grid import observed_cells, world_cell
from gsmn.model.readout import Heads

MAPS = ("semantic", "relevance", "goal")
KEYS = {"semantic": "semantic_map_w", "relevance": "relevance_map_w", "goal": "goal_map_w"}
LABELS = {"semantic": "perfect perception", "relevance": "perfect grounding", "goal": "perfect goal"}
FLAGS = tuple(f"truth-{m}" for m in MAPS)  # `gsmn eval --intervene`
FLAG_LABELS = {f"truth-{m}": LABELS[m] for m in MAPS}
CODES_FILE = "map_codes.safetensors"
MAX_PAINTS = 32
GOAL_WINDOW = 4  # r: the goal template spans (2r+1)^2 cells, 3.75 m each way at 0.9375 m cells


class InterventionError(ValueError):
    """An intervention that cannot be made, with the reason in words."""


@dataclass(frozen=True)
class Paint:
    """One painted edit: "peak" puts the named landmark's code (relevance) or a goal peak (goal) at x, y; "erase"
    puts the background in the disk of `radius` metres around x, y."""

    op: str
    x: float
    y: float
    radius: float = 1.5


@dataclass(frozen=True)
class Intervention:
    map: str  # "semantic", "relevance" or "goal"
    source: str = "truth"  # "truth" or "painted"
    hold: bool = True
    paint: tuple[Paint, ...] = ()

    def describe(self) -> str:
        if self.source == "truth":
            how = "held at every step" if self.hold else "written once into the semantic map"
            return f"{LABELS[self.map]}: the true {self.map} map, {how}"
        edits = ", ".join(f"{p.op} at ({p.x:.1f}, {p.y:.1f})" for p in self.paint)
        return f"painted {self.map} map ({edits}), held at every step"

    def short(self) -> str:
        """In a few words: "perfect goal", "a painted goal map"."""
        return LABELS[self.map] if self.source == "truth" else f"a painted {self.map} map"

    def to_dict(self) -> dict:
        d = {"map": self.map, "with": self.source, "hold": self.hold}
        if self.paint:
            d["paint"] = [{"op": p.op, "x": p.x, "y": p.y, "radius": p.radius} for p in self.paint]
        return d


def parse_intervention(d: dict, field_size: float = 30.0) -> Intervention:
    """An intervention from its JSON form, e.g. {"map": "goal", "with": "truth", "hold": true}, or
    {"map": "goal", "with": "painted", "paint": [{"op": "peak", "x": 12, "y": 20}]}; InterventionError says what
    is wrong."""
    if not isinstance(d, dict):
        raise InterventionError("an intervention is an object such as {\"map\": \"goal\", \"with\": \"truth\"}")
    unknown = set(d) - {"map", "with", "hold", "paint"}
    if unknown:
        raise InterventionError(f"unknown intervention field(s) {sorted(unknown)}; use map, with, hold, paint")
    name, source, hold = d.get("map"), d.get("with", "truth"), d.get("hold", True)
    if name not in MAPS:
        raise InterventionError(f"map must be one of {', '.join(MAPS)}, not {name!r}")
    if source not in ("truth", "painted"):
        raise InterventionError(f"with must be 'truth' or 'painted', not {source!r}")
    if not isinstance(hold, bool):
        raise InterventionError("hold must be true or false")
    if not hold and (name != "semantic" or source != "truth"):
        raise InterventionError("only the true semantic map can be written once (hold: false): the relevance and "
                                "goal maps are made afresh from the semantic map at every step, so they can only "
                                "be held")
    paints = d.get("paint") or []
    if source == "painted":
        if name == "semantic":
            raise InterventionError("paint the relevance or goal map; the semantic map's feature channels have no "
                                    "single value to paint (use with: truth)")
        if not isinstance(paints, list) or not paints:
            raise InterventionError("a painted map needs a non-empty paint list, e.g. [{\"op\": \"peak\", "
                                    "\"x\": 12.0, \"y\": 20.5}]")
        if len(paints) > MAX_PAINTS:
            raise InterventionError(f"at most {MAX_PAINTS} paints, not {len(paints)}")
    elif paints:
        raise InterventionError("paint goes with with: painted")
    return Intervention(name, source, hold, tuple(_paint(p, field_size) for p in paints))


def _paint(p: dict, field_size: float) -> Paint:
    if not isinstance(p, dict) or p.get("op") not in ("peak", "erase"):
        raise InterventionError(f"each paint is {{\"op\": \"peak\" or \"erase\", \"x\", \"y\"[, \"radius\"]}}, "
                                f"not {p!r}")
    try:
        x, y, radius = float(p["x"]), float(p["y"]), float(p.get("radius", 1.5))
    except (KeyError, TypeError, ValueError) as e:
        raise InterventionError(f"a paint needs numbers x and y (metres), got {p!r}") from e
    if not (0 <= x <= field_size and 0 <= y <= field_size):
        raise InterventionError(f"paint at ({x}, {y}) is off the field [0, {field_size:g}] m")
    if not 0 < radius <= field_size:
        raise InterventionError(f"a paint's radius must be in (0, {field_size:g}] m, not {radius}")
    return Paint(p["op"], x, y, radius)


def paint_from_text(text: str) -> list[dict]:
    """Paint typed as words, e.g. "peak 12 20; erase 5 5 2" (op x y [radius], metres, separated by ';'), as the
    JSON form `parse_intervention` takes; InterventionError says which part it cannot read."""
    out = []
    for part in (p.strip() for p in text.split(";")):
        if not part:
            continue
        words = part.split()
        try:
            numbers = [float(w) for w in words[1:]]
        except ValueError:
            numbers = []
        if not words or words[0] not in ("peak", "erase") or len(numbers) not in (2, 3):
            raise InterventionError(f"cannot read the paint {part!r}: write 'peak X Y' or 'erase X Y [RADIUS]' "
                                    "(metres)")
        paint = {"op": words[0], "x": numbers[0], "y": numbers[1]}
        out.append(paint | ({"radius": numbers[2]} if len(numbers) == 3 else {}))
    return out


def intervention_from_flag(flag: str) -> Intervention:
    """`gsmn eval --intervene truth-semantic|truth-relevance|truth-goal`."""
    if flag not in FLAGS:
        raise InterventionError(f"--intervene takes one of {', '.join(FLAGS)}, not {flag!r}")
    return Intervention(flag.removeprefix("truth-"))


# -- the model's own coding --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MapCodes:
    semantic_class: np.ndarray  # (K, C_f) per landmark class
    semantic_known: np.ndarray  # (K,) bool: the class was seen in calibration (else from the head's direction)
    semantic_background: np.ndarray  # (C_f,)
    relevance_named: np.ndarray  # (3,)
    relevance_other: np.ndarray  # (3,)
    relevance_background: np.ndarray  # (3,)
    goal_template: np.ndarray  # (2, 2r+1, 2r+1) around the goal cell
    goal_background: np.ndarray  # (2,)
    meta: dict = field(default_factory=dict)  # calibration: environments, successes, weights digest

    def save(self, path: Path | str) -> None:
        from safetensors.numpy import save_file

        arrays = {k: np.ascontiguousarray(getattr(self, k)) for k in ARRAYS}
        arrays["semantic_known"] = arrays["semantic_known"].astype(np.uint8)
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        try:
            save_file(arrays, str(tmp), metadata={"meta": json.dumps(self.meta)})
            tmp.replace(path)  # a reader sees the old file or the new one, never half of one
        finally:
            tmp.unlink(missing_ok=True)

    @classmethod
    def load(cls, path: Path | str) -> MapCodes:
        from safetensors import SafetensorError, safe_open

        try:
            with safe_open(str(path), framework="numpy") as f:
                arrays = {k: f.get_tensor(k) for k in ARRAYS}
                meta = json.loads((f.metadata() or {}).get("meta", "{}"))
        except (SafetensorError, OSError, KeyError, ValueError) as e:
            raise InterventionError(f"the map codes in {path} cannot be read ({e}); derive them again with "
                                    "`gsmn map-codes --checkpoint FOLDER`") from e
        arrays["semantic_known"] = arrays["semantic_known"].astype(bool)
        return cls(**arrays, meta=meta)


ARRAYS = ("semantic_class", "semantic_known", "semantic_background", "relevance_named", "relevance_other",
          "relevance_background", "goal_template", "goal_background")


def weights_digest(folder: Path | str) -> str:
    """sha256 of a checkpoint's weights file (the codes belong to those weights)."""
    h = hashlib.sha256()
    with open(Path(folder) / "weights.safetensors", "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def codes_for(folder: Path | str) -> MapCodes:
    """The map codes beside a checkpoint; InterventionError when missing or made for other weights."""
    folder = Path(folder)
    path = folder / CODES_FILE
    if not path.is_file():
        raise InterventionError(f"{folder} has no map codes ({CODES_FILE}), which a map intervention needs to write "
                                f"a map in the model's own coding: run `gsmn map-codes --checkpoint {folder}` "
                                "(flies 40 dev environments, a few minutes)")
    codes = MapCodes.load(path)
    if codes.meta.get("weights_sha256") != weights_digest(folder):
        raise InterventionError(f"the map codes in {folder} were derived for other weights; derive them again with "
                                f"`gsmn map-codes --checkpoint {folder}`")
    return codes


def derive_codes(finals: Sequence[tuple[TruthMaps, np.ndarray, np.ndarray, np.ndarray, bool]], heads: Heads,
                 meta: dict | None = None) -> MapCodes:
    """The codes from calibration flights: for each, (truth, semantic_w (C_f, n, n), relevance_w (3, n, n),
    goal_w (2, n, n), success), the maps at the episode's last step."""
    if not finals:
        raise InterventionError("no calibration flights to derive map codes from")
    K, C = heads.perception_w.shape
    sums, counts = np.zeros((K, C)), np.zeros(K)
    bg, bg_n = np.zeros(C), 0
    right = [f for f in finals if f[4]] or list(finals)  # the relevance and goal codes: successes, if any
    for truth, semantic, _, _, _ in finals:
        seen = observed_cells(semantic)
        s = semantic.astype(np.float64)
        for k in np.unique(truth.class_id[seen & (truth.class_id >= 0)]):
            cells = seen & (truth.class_id == k)
            sums[k] += s[:, cells].sum(1)
            counts[k] += cells.sum()
        back = seen & (truth.class_id < 0)
        bg += s[:, back].sum(1)
        bg_n += back.sum()
    background = bg / max(bg_n, 1)
    known = counts > 0
    semantic_class = np.where(known[:, None], sums / np.maximum(counts, 1)[:, None], 0.0)
    reach = np.linalg.norm(semantic_class[known] - background, axis=1).mean() if known.any() else 1.0
    w = heads.perception_w.astype(np.float64)
    direction = w - w.mean(0)
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-9)
    semantic_class[~known] = background + reach * direction[~known]
    rel = {name: _mean_over(right, 2, lambda t, seen, m=mask: seen & m(t))
           for name, mask in (("named", lambda t: t.named), ("other", lambda t: (t.landmark >= 0) & ~t.named),
                              ("background", lambda t: t.landmark < 0))}
    template, goal_bg = _goal_template([(f[0], f[1], f[3]) for f in right])
    meta = dict(meta or {})
    meta.update(classes_seen=int(known.sum()), episodes=len(finals), successes=sum(bool(f[4]) for f in finals),
                relevance_goal_from="successes" if any(f[4] for f in finals) else "all flights (no success)")
    f32 = np.float32
    return MapCodes(semantic_class.astype(f32), known, background.astype(f32), rel["named"].astype(f32),
                    rel["other"].astype(f32), rel["background"].astype(f32), template.astype(f32),
                    goal_bg.astype(f32), meta)


def _mean_over(finals, index: int, select) -> np.ndarray:
    total, n = None, 0
    for f in finals:
        cells = select(f[0], observed_cells(f[1]))
        values = f[index].astype(np.float64)[:, cells]
        total = values.sum(1) if total is None else total + values.sum(1)
        n += cells.sum()
    return total / max(n, 1)


def _goal_template(finals) -> tuple[np.ndarray, np.ndarray]:
    r = GOAL_WINDOW
    C, n = finals[0][2].shape[0], finals[0][2].shape[-1]
    sums, counts = np.zeros((C, 2 * r + 1, 2 * r + 1)), np.zeros((2 * r + 1, 2 * r + 1))
    far, far_n = np.zeros(C), 0
    rows, cols = np.mgrid[0:n, 0:n]
    for truth, _, goal in finals:
        g = goal.astype(np.float64)
        gr, gc = truth.goal_cell
        near = (np.abs(rows - gr) <= r) & (np.abs(cols - gc) <= r)
        sums[:, rows[near] - gr + r, cols[near] - gc + r] += g[:, near]
        counts[rows[near] - gr + r, cols[near] - gc + r] += 1
        far += g[:, ~near].sum(1)
        far_n += (~near).sum()
    background = far / max(far_n, 1)
    template = np.where(counts > 0, sums / np.maximum(counts, 1), background[:, None, None])
    return template, background


# -- substitutes ------------------------------------------------------------------------------------------------
def _disk(x: float, y: float, radius: float, n: int, field_size: float) -> np.ndarray:
    s = field_size / n
    cx = (np.arange(n) + 0.5) * s
    cy = field_size - (np.arange(n) + 0.5) * s
    return np.hypot(cx[None, :] - x, cy[:, None] - y) <= max(radius, s / 2)


def _stamp(out: np.ndarray, template: np.ndarray, row: int, col: int) -> np.ndarray:
    """`template` (C, 2r+1, 2r+1) written into `out` (C, n, n) centred on (row, col), clipped; the written mask."""
    r = template.shape[-1] // 2
    n = out.shape[-1]
    mask = np.zeros(out.shape[-2:], bool)
    r0, r1, c0, c1 = max(row - r, 0), min(row + r + 1, n), max(col - r, 0), min(col + r + 1, n)
    out[:, r0:r1, c0:c1] = template[:, r0 - row + r:r1 - row + r, c0 - col + r:c1 - col + r]
    mask[r0:r1, c0:c1] = True
    return mask


def truth_map(name: str, truth: TruthMaps, codes: MapCodes) -> np.ndarray:
    """The true map `name` over the whole field in the model's coding, (C, n, n)."""
    n = truth.landmark.shape[0]
    if name == "semantic":
        out = np.broadcast_to(codes.semantic_background[:, None, None], (codes.semantic_background.size, n, n)).copy()
        inside = truth.class_id >= 0
        out[:, inside] = codes.semantic_class[truth.class_id[inside]].T
        return out
    if name == "relevance":
        out = np.broadcast_to(codes.relevance_background[:, None, None], (3, n, n)).copy()
        out[:, (truth.landmark >= 0) & ~truth.named] = codes.relevance_other[:, None]
        out[:, truth.named] = codes.relevance_named[:, None]
        return out
    out = np.broadcast_to(codes.goal_background[:, None, None], (codes.goal_background.size, n, n)).copy()
    _stamp(out, codes.goal_template, *truth.goal_cell)
    return out


def painted_edits(name: str, paints: Sequence[Paint], codes: MapCodes, n: int, field_size: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(mask (n, n), values (C, n, n)): the cells the paints set and what they set them to, in order."""
    if name == "relevance":
        background, peak = codes.relevance_background, codes.relevance_named
    else:
        background, peak = codes.goal_background, None
    values = np.zeros((background.size, n, n), np.float32)
    mask = np.zeros((n, n), bool)
    for p in paints:
        if p.op == "erase" or name == "relevance":
            disk = _disk(p.x, p.y, p.radius, n, field_size)
            values[:, disk] = (background if p.op == "erase" else peak)[:, None]
            mask |= disk
        else:
            row, col = world_cell(p.x, p.y, field_size, n)
            stamp = values.copy()
            written = _stamp(stamp, codes.goal_template, min(max(row, 0), n - 1), min(max(col, 0), n - 1))
            values[:, written] = stamp[:, written]
            mask |= written
    return mask, values


class Substitute:
    """What an intervened model uses in place of its map at each step: `(key, fresh) -> map`, for the model's
    `ground`/`step` (`gsmn.model.gsmn.GSMN`); keys other than the intervened map's pass through."""

    def __init__(self, intervention: Intervention, codes: MapCodes, truth: TruthMaps, field_size: float):
        self.intervention = intervention
        self.key = KEYS[intervention.map]
        n = truth.landmark.shape[0]
        if intervention.source == "truth":
            self.mask = None
            self.values = torch.from_numpy(truth_map(intervention.map, truth, codes))
        else:
            mask, values = painted_edits(intervention.map, intervention.paint, codes, n, field_size)
            self.mask, self.values = torch.from_numpy(mask), torch.from_numpy(values)
        background = {"semantic": codes.semantic_background, "relevance": codes.relevance_background,
                      "goal": codes.goal_background}[intervention.map]
        self.background = torch.from_numpy(np.asarray(background, np.float32))[:, None, None]
        self.written = False

    def __call__(self, key: str, fresh: torch.Tensor) -> torch.Tensor:
        if key != self.key or (self.written and not self.intervention.hold):
            return fresh
        self.written = True
        values = self.values.to(fresh.dtype)
        if self.mask is None:
            return values.expand_as(fresh)
        return torch.where(self.mask, values, fresh)

    def outside(self, key: str) -> torch.Tensor | None:
        """What the substituted map holds beyond the field (its background), for the drone-frame view."""
        return self.background if key == self.key else None


class InterventionMaker:
    """Makes an episode's `Substitute` from its task: what `gsmn.model.policy.ModelPolicy.intervene` takes."""

    def __init__(self, intervention: Intervention, codes: MapCodes, map_size: int, success_radius: float):
        self.intervention, self.codes = intervention, codes
        self.map_size, self.success_radius = map_size, success_radius

    def __call__(self, task) -> Substitute:
        truth = truth_maps(task.world, task.instruction, self.map_size, self.success_radius)
        return Substitute(self.intervention, self.codes, truth, task.world.field_size)


def check_model(model) -> None:
    """A map intervention needs GSMN with both filters (the maps it substitutes); else InterventionError."""
    m = model.config.model
    if getattr(model, "kind", None) not in ("gsmn", "gsmn-no-plan") or not (m.grounding_filter and m.goal_filter):
        raise InterventionError(f"a map intervention needs a GSMN with its grounding and goal filters; this "
                                f"{getattr(model, 'kind', type(model).__name__)!r} model has other maps")
