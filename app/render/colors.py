"""Colours for the model's maps: colormaps with their range, the semantic map as "most likely landmark per
cell" with a legend (over every class the head knows, or over this world's landmarks and "nothing"), the colours
of the 3D view's paths and markers with their legend, crisp nearest-neighbour upscaling and PNG encoding.

Pure numpy and Pillow, no torch and no viser, so it is cheap to test. Maps arrive north-up (row 0 is the
north edge of the field, see docs/model.md) and stay that way: images are drawn as they are stored.
"""

from __future__ import annotations

import base64
import colorsys
import html
import io

import numpy as np
from PIL import Image

from gsmn.model.heads import softmax

# matplotlib's viridis at nine evenly spaced points; linear interpolation between them is within a few
# levels of the full table and keeps the map perceptually ordered and readable for colour-blind people.
_VIRIDIS = np.array([(68, 1, 84), (71, 44, 122), (59, 81, 139), (44, 113, 142), (33, 144, 141), (39, 173, 129),
                     (92, 200, 99), (170, 220, 50), (253, 231, 37)], dtype=np.float64)
# A diverging map (blue - white - red) for signed values such as raw relevance channels.
_DIVERGING = np.array([(33, 102, 172), (103, 169, 207), (209, 229, 240), (247, 247, 247), (253, 219, 199),
                       (239, 138, 98), (178, 24, 43)], dtype=np.float64)
COLORMAPS = {"viridis": _VIRIDIS, "diverging": _DIVERGING}

UNSEEN_RGB = (96, 96, 104)  # cells the camera has never covered: dark grey, with its swatch in the legend
OTHER_RGB = (236, 228, 210)  # cells read as a landmark class this world does not have (the head has no "ground")
NOTHING = "nothing"  # the world reading's entry for "none of this world's landmarks": drawn in OTHER_RGB
# The 3D view's colours (app.page.scene), after the paper's figures, and what each means in plain words
# (`paths_legend_html`): demonstration red, the flight blue, the correct side green, a what-if gold.
DEMO_RGB = (220, 40, 40)
POLICY_RGB = (40, 110, 245)
QUADRANT_RGB = (60, 200, 90)
COUNTERFACTUAL_RGB = (245, 190, 30)
DRONE_MARK_RGB = (255, 214, 0)  # presenter mode's ring around the drone
PATHS_LEGEND = ((POLICY_RGB, "blue line: the path the drone flew"),
                (DEMO_RGB, "red line: the demonstration path to the goal (red post)"),
                (QUADRANT_RGB, "green wedge: the side to stop on"))


def _lut(name: str) -> np.ndarray:
    anchors = COLORMAPS[name]
    x = np.linspace(0.0, 1.0, len(anchors))
    t = np.linspace(0.0, 1.0, 256)
    return np.stack([np.interp(t, x, anchors[:, k]) for k in range(3)], 1).round().astype(np.uint8)  # (256, 3)


_LUTS = {name: _lut(name) for name in COLORMAPS}


def apply_colormap(values: np.ndarray, vmin: float, vmax: float, cmap: str = "viridis") -> np.ndarray:
    """Scalar map (H, W) -> RGB uint8 (H, W, 3), values clipped to [vmin, vmax]; NaN shows as the low end."""
    v = np.nan_to_num(np.asarray(values, dtype=np.float64), nan=vmin)
    span = vmax - vmin if vmax > vmin else 1.0
    index = np.clip((v - vmin) / span * 255.0, 0, 255).astype(np.uint8)
    return _LUTS[cmap][index]


def _cells(mask: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    """The cells a picture's ranges are taken over: `mask` where it holds any, else all of them."""
    return np.asarray(mask, bool) if mask is not None and np.asarray(mask).any() else np.ones(shape, bool)


def channels_rgb(maps: np.ndarray, mask: np.ndarray | None = None,
                 shared: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Up to three channels (C, H, W) as one picture: channel 0 red, 1 green, 2 blue, each scaled to its own range
    over the cells in `mask` (all cells when none is set), or all to one range when `shared` (so a channel that
    barely varies stays flat instead of being stretched). Returns the RGB uint8 (H, W, 3) and the brightest
    channel's scaled value per cell (H, W) in [0, 1]."""
    maps = np.asarray(maps, np.float64)[:3]
    inside = _cells(mask, maps.shape[1:])
    ranges = [(maps[:, inside].min(), maps[:, inside].max())] * len(maps) if shared else \
        [(m[inside].min(), m[inside].max()) for m in maps]
    scaled = np.zeros((3, *maps.shape[1:]))
    for k, (m, (lo, hi)) in enumerate(zip(maps, ranges, strict=True)):
        scaled[k] = np.clip((m - lo) / (hi - lo), 0.0, 1.0) if hi - lo > 1e-6 else 0.0
    return (np.moveaxis(scaled, 0, -1) * 255).round().astype(np.uint8), scaled.max(0)


def principal_components(maps: np.ndarray, mask: np.ndarray | None = None, k: int = 3) -> np.ndarray:
    """A many-channel map (C, H, W) reduced to its k principal components over the cells in `mask` (all cells when
    none is set), as a (k, H, W) map for `channels_rgb`: cells of like colour hold like features. Each component's
    sign is set so that its largest loading is positive, which keeps the colours steady from one step to the next.
    Draw them with `channels_rgb(..., shared=True)`, so that a weak component stays weak."""
    maps = np.asarray(maps, np.float64)
    C, H, W = maps.shape
    x = maps.reshape(C, -1).T  # (H*W, C)
    seen = x[_cells(mask, (H, W)).reshape(-1)]
    centre = seen.mean(0)
    vt = np.linalg.svd(seen - centre, full_matrices=False)[2][:k]
    vt *= np.sign(vt[np.arange(len(vt)), np.abs(vt).argmax(1)])[:, None]
    out = np.zeros((k, H, W))
    out[: len(vt)] = ((x - centre) @ vt.T).T.reshape(len(vt), H, W)
    return out


def channels_legend_html(label: str, channels: int = 3, name: str = "channel", start: int = 0) -> str:
    """The legend of `channels_rgb`: one swatch per channel ("channel 0", or `name` and the index from `start`),
    and what the picture shows."""
    swatches = "".join(f'<span style="display:inline-block;width:10px;height:10px;border-radius:2px;'
                       f'background:rgb{rgb};margin:0 3px 0 6px;vertical-align:middle"></span>{name} {k}'
                       for k, rgb in enumerate(((255, 0, 0), (0, 255, 0), (0, 0, 255))[:channels], start))
    return (f'<div style="font-size:11px;line-height:1.4"><div>{swatches}</div>'
            f'<div style="opacity:.75">{html.escape(label)}</div></div>')


def css_gradient(cmap: str = "viridis") -> str:
    stops = ", ".join(f"rgb({r},{g},{b})" for r, g, b in COLORMAPS[cmap].astype(int))
    return f"linear-gradient(to right, {stops})"


def colorbar_html(vmin: float, vmax: float, cmap: str = "viridis", label: str = "") -> str:
    """A horizontal colour bar with its range, as a small HTML block."""
    return (f'<div style="font-size:11px;line-height:1.2">'
            f'<div style="height:8px;border-radius:2px;background:{css_gradient(cmap)}"></div>'
            f'<div style="display:flex;justify-content:space-between"><span>{_fmt(vmin)}</span>'
            f'<span style="opacity:.75">{html.escape(label)}</span><span>{_fmt(vmax)}</span></div></div>')


def _fmt(x: float) -> str:
    return f"{x:.2g}" if abs(x) < 0.01 and x != 0 else f"{x:.2f}"


def class_palette(n: int) -> np.ndarray:
    """n distinct colours (n, 3) uint8: golden-ratio hues, alternating saturation and value so that
    neighbours in the catalogue (often similar objects) differ in more than hue."""
    out = np.empty((n, 3), np.uint8)
    for i in range(n):
        h = (0.07 + i * 0.618033988749895) % 1.0
        s = (0.85, 0.55, 0.95)[i % 3]
        v = (0.95, 0.80, 0.65)[(i // 3) % 3]
        out[i] = np.array(colorsys.hsv_to_rgb(h, s, v)) * 255
    return out


def class_probabilities(semantic_map: np.ndarray, weight: np.ndarray, bias: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """The perception head on every cell: semantic map (C, H, W), head Linear(C -> K) as weight (K, C) and bias (K,)
    -> (P(class) (K, H*W), observed (H*W,) bool).

    A cell the camera never covered holds exactly zero in every channel (the map starts at zero and only the
    covered cells are blended), so those are marked unobserved rather than given a meaningless class."""
    C, H, W = semantic_map.shape
    features = semantic_map.reshape(C, H * W).astype(np.float32)
    # einsum, not @: numpy's threaded BLAS spins for ~16 ms on this tiny product when the cores are busy
    logits = np.einsum("kc,cn->kn", weight.astype(np.float32), features) + bias.astype(np.float32)[:, None]
    return softmax(logits, axis=0), np.abs(features).max(0) > 1e-6


def semantic_classes(semantic_map: np.ndarray, weight: np.ndarray, bias: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The perception head's most likely class per cell: -> (class (H, W) int, its probability (H, W), observed
    (H, W) bool); see `class_probabilities`."""
    H, W = semantic_map.shape[1:]
    probs, observed = class_probabilities(semantic_map, weight, bias)
    return probs.argmax(0).reshape(H, W), probs.max(0).reshape(H, W), observed.reshape(H, W)


def world_reading(semantic_map: np.ndarray, weight: np.ndarray, bias: np.ndarray, names, world_names
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The perception head read as "which of this world's landmarks, or nothing": per cell, P(name) for each name
    of the sorted `world_names` (the classes of that name, `names` per class, summed) and P(nothing) = the rest
    (every class this world does not have), and the likeliest of those. -> (index (H, W) int into the sorted names,
    -1 for nothing; its probability (H, W); observed (H, W) bool).

    The head has no "open ground" class (it is trained at landmark cells only), so on open ground its argmax over
    all 63 classes names landmarks that are not there; here those cells read "nothing" unless one of this world's
    landmarks is likelier than all the absent ones together."""
    H, W = semantic_map.shape[1:]
    probs, observed = class_probabilities(semantic_map, weight, bias)
    order = sorted(set(world_names))
    member = np.array([[name == n for name in names] for n in order], np.float32).reshape(len(order), len(names))
    p_names = np.einsum("wk,kn->wn", member, probs)  # (n, H*W)
    p = np.vstack([p_names, 1.0 - p_names.sum(0, keepdims=True)])  # the last row: nothing
    best = p.argmax(0)
    index = np.where(best == len(order), -1, best)
    return index.reshape(H, W), p.max(0).reshape(H, W), observed.reshape(H, W)


def semantic_rgb(classes: np.ndarray, confidence: np.ndarray, observed: np.ndarray, palette: np.ndarray,
                 n_classes: int | None = None) -> np.ndarray:
    """Class per cell -> RGB (H, W, 3): the class colour, darker where the head is less sure (brightness from
    0.45 at chance to 1 at certainty), class -1 (`world_classes`: not in this world) pale, unobserved cells grey."""
    K = max(n_classes or len(palette), 2)  # the head's classes: chance is 1 / 63 whatever the palette shown
    chance = 1.0 / K
    shade = 0.45 + 0.55 * np.clip((confidence - chance) / (1.0 - chance), 0.0, 1.0)
    table = np.vstack([palette.reshape(-1, 3), np.array([OTHER_RGB], np.uint8)]).astype(np.float32)
    rgb = table[np.where(classes < 0, len(table) - 1, classes)] * shade[..., None]
    rgb[(classes < 0) & observed] = OTHER_RGB  # another world's class: one flat pale colour, never a dark grey
    rgb[~observed] = UNSEEN_RGB
    return rgb.round().astype(np.uint8)


def world_classes(classes: np.ndarray, names: list[str] | tuple[str, ...], world_names) -> np.ndarray:
    """Map the perception head's class per cell onto this world's landmark names: (H, W) int, the index of the
    cell's name in the sorted `world_names`, or -1 where the head reads a class this world does not have.

    The head has no "open ground" class (it is trained at landmark cells only), so on open ground it names any of
    the 63 classes; a legend of those would list palm trees and arches that are not there. Two catalogue models
    with one name (tower_1, tower_2) are one name here."""
    order = sorted(set(world_names))
    index = {name: k for k, name in enumerate(order)}
    lookup = np.array([index.get(name, -1) for name in names], np.int64)
    return lookup[classes]


def name_palette(names: list[str] | tuple[str, ...], world_names) -> np.ndarray:
    """A colour per name of this world (sorted), each its catalogue class's colour (the first class of that name),
    so a landmark keeps its colour from world to world."""
    palette = class_palette(len(names))
    first = {}
    for k, name in enumerate(names):
        first.setdefault(name, k)
    return np.array([palette[first[name]] for name in sorted(set(world_names))], np.uint8).reshape(-1, 3)


def semantic_legend_html(classes: np.ndarray, observed: np.ndarray, palette: np.ndarray, names: list[str],
                         top: int = 8, other: bool = False) -> str:
    """The classes covering most observed cells, with their colour and share of the observed area; `other`: the
    class -1 ("read as a class this world does not have") gets its own entry. Names shared by several classes are
    counted once. The grey of unobserved cells is named only when there are some."""
    seen = classes[observed].ravel()
    total = max(int(seen.size), 1)
    shares: dict[str, float] = {}
    colours: dict[str, tuple[int, int, int]] = {}
    for k in np.unique(seen):
        k = int(k)
        name = "other classes (not in this world)" if k < 0 else names[k]
        shares[name] = shares.get(name, 0.0) + float((seen == k).sum()) / total
        colours.setdefault(name, OTHER_RGB if k < 0 else tuple(int(c) for c in palette[k]))
    order = sorted(shares, key=lambda name: -shares[name])[:top]
    return _legend([swatch_html(colours[name], f"{name} {100 * shares[name]:.0f}%") for name in order], observed)


def world_legend_html(index: np.ndarray, observed: np.ndarray, palette: np.ndarray, names: list[str]) -> str:
    """The legend of `world_reading`: every one of this world's landmarks (`names`, sorted, as the index counts
    them) in that order, whether or not any cell reads it, then "nothing", each with its share of the observed
    cells, so the entries stay in place from step to step."""
    seen = index[observed].ravel()
    total = max(int(seen.size), 1)
    items = [swatch_html(tuple(int(c) for c in palette[k]), f"{name} {100 * (seen == k).sum() / total:.0f}%")
             for k, name in enumerate(names)]
    items.append(swatch_html(OTHER_RGB, f"{NOTHING} (none of these) {100 * (seen < 0).sum() / total:.0f}%"))
    return _legend(items if seen.size else [], observed)


def swatch_html(rgb, label: str) -> str:
    """One legend entry: a small square of the colour, then its label."""
    r, g, b = rgb
    return (f'<span style="white-space:nowrap;margin-right:6px"><span style="display:inline-block;width:9px;'
            f'height:9px;border-radius:2px;background:rgb({r},{g},{b});margin-right:3px;'
            f'box-shadow:inset 0 0 0 1px rgba(0,0,0,.15)"></span>{html.escape(label)}</span>')


def _legend(items: list[str], observed: np.ndarray) -> str:
    """A semantic legend's entries, and the grey of the cells not seen yet when there are some."""
    if not items:
        return '<div class="gsmn-legend" style="font-size:11px;opacity:.75">nothing observed yet</div>'
    unseen = (~observed).mean()
    if unseen > 0:
        items.append(swatch_html(UNSEEN_RGB, f"not seen yet {100 * unseen:.0f}% of the map"))
    return f'<div class="gsmn-legend" style="font-size:11px;line-height:1.5">{"".join(items)}</div>'


def paths_legend_html() -> str:
    """What the 3D view's lines and wedge mean, in plain words."""
    items = "".join(swatch_html(rgb, label) for rgb, label in PATHS_LEGEND)
    return f'<div class="gsmn-paths-legend" style="font-size:11px;line-height:1.5">In the 3D view: {items}</div>'


def upscale(image: np.ndarray, factor: int) -> np.ndarray:
    """Nearest-neighbour upscaling (H, W[, C]) -> (H f, W f[, C]): every cell stays a sharp square."""
    return np.repeat(np.repeat(image, factor, axis=0), factor, axis=1)


def with_alpha(rgb: np.ndarray, alpha: float | np.ndarray) -> np.ndarray:
    """RGB (H, W, 3) + opacity in [0, 1] (scalar or (H, W)) -> RGBA uint8."""
    a = np.broadcast_to(np.clip(np.asarray(alpha, dtype=np.float32), 0, 1) * 255, rgb.shape[:2])
    return np.concatenate([rgb, a.round().astype(np.uint8)[..., None]], axis=-1)


def png_bytes(image: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buffer, format="PNG", compress_level=1)
    return buffer.getvalue()


def decode_image(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")
