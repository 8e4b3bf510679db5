"""The landmark catalogue: the pool of 63 procedurally built 3D landmark models.

This implements the landmark pool of the paper's "Environment" section (Blukis et al., "Following
High-level Navigation Instructions on a Simulated Quadcopter with Imitation Learning", RSS 2018): every
environment is a 30 m x 30 m grassy field holding 6-13 landmarks drawn from a pool of 63 models, which
are referred to by 45 unique noun phrases.  Eleven phrases are shared ("palm tree" x4, "rock" x4,
"house" x3, "barrel" x3, "bush" x3 and "well", "mushroom", "cone", "box", "christmas tree", "tower" x2
each); the other 34 models have a phrase of their own.

Every model is assembled from trimesh primitives (boxes, cylinders, cones, icospheres, tori, solids of
revolution and hand-built extrusions) plus rigid transforms, so the catalogue needs no external files;
rock-like jitter comes from a fixed-seed generator, so ``build()`` is byte-for-byte deterministic.

Conventions: metres, z up, the footprint centred on x = y = 0, resting on z = 0.  ``radius`` is the
model's radius class (the goal point of an instruction is placed ``radius`` from the centre); the mesh
stays within ``0.8 * radius`` horizontally and the vertical axis x = y = 0 passes through solid material.
Each model is a list of parts, one flat colour per part.  The names, phrases and radius classes are data in
``gsmn.world.catalogue`` (its order is the class id used by the perception head); ``CATALOGUE`` here pairs each
entry with its builder, registered by ``@landmark(name)``.  ``gsmn.world.assets`` writes the built meshes to
disk for the simulator and viewer.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import trimesh
from trimesh import creation
from trimesh import transformations as tf

from gsmn.world.catalogue import CATALOGUE as CLASSES
from gsmn.world.catalogue import NOUN_PHRASES  # noqa: F401 - re-exported

RGBA = tuple[float, float, float, float]
Vec = Sequence[float]


@dataclass(frozen=True)
class LandmarkPart:
    """One flat-coloured piece of a landmark."""

    mesh: trimesh.Trimesh
    rgba: RGBA  # values in [0, 1], alpha 1


@dataclass(frozen=True)
class LandmarkModel:
    """A catalogue entry: identity, noun phrase, radius class and a deterministic mesh builder."""

    name: str  # unique snake_case id, e.g. "fir_tree", "rock_2"
    noun_phrase: str  # lower-case words used in instructions, e.g. "fir tree", "rock"
    radius: float  # radius class in metres, 2.25 .. 3.75
    build: Callable[[], list[LandmarkPart]]


def hex_rgba(colour: str) -> RGBA:
    """'#rrggbb' -> (r, g, b, 1.0) with channels in [0, 1]."""
    h = colour.lstrip("#")
    return (int(h[0:2], 16) / 255.0, int(h[2:4], 16) / 255.0, int(h[4:6], 16) / 255.0, 1.0)


# --------------------------------------------------------------------------------------------------
# Palette.  Saturated, mutually distinct colours so that a CNN can separate classes in small images.
# --------------------------------------------------------------------------------------------------
BARK = "#6b4423"
BARK_DARK = "#4e3019"
PALM_BARK = "#a47a4c"
PALM_BARK_DARK = "#7d5a35"
WOOD = "#8a5a32"
WOOD_LIGHT = "#c8924f"
WOOD_DARK = "#5e3b1e"
WHITE = "#f4f4f2"
BLACK = "#1c1c1e"
DARK_GREY = "#3a3d42"
GREY = "#8e9196"
LIGHT_GREY = "#c4c7cc"
RED = "#d7191c"
ORANGE = "#ff6f0f"
YELLOW = "#f7c600"
GOLD = "#f2b51d"
BLUE = "#1f5fd1"
NAVY = "#1f3561"
SKY = "#7cc4f2"
WATER = "#2f80e0"
PINK = "#ff4fa3"
PURPLE = "#7d3cc8"
MAGENTA = "#d6309c"
CYAN = "#1aa3e0"
TEAL = "#15858c"
STONE = "#9a9a98"
SAND = "#dcb862"

# --------------------------------------------------------------------------------------------------
# Geometry helpers.  Every helper returns a fresh trimesh.Trimesh in world coordinates.
# --------------------------------------------------------------------------------------------------


def _mesh(vertices: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    return trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64), process=False)


def place(mesh: trimesh.Trimesh, at: Vec = (0.0, 0.0, 0.0), rx: float = 0.0, ry: float = 0.0,
          rz: float = 0.0) -> trimesh.Trimesh:
    """Rotate about the x, then y, then z axis through the origin (degrees), then translate by `at`."""
    for deg, axis in ((rx, (1, 0, 0)), (ry, (0, 1, 0)), (rz, (0, 0, 1))):
        if deg:
            mesh.apply_transform(tf.rotation_matrix(math.radians(deg), axis))
    mesh.apply_translation(at)
    return mesh


def block(sx: float, sy: float, sz: float, x: float = 0.0, y: float = 0.0, z: float = 0.0) -> trimesh.Trimesh:
    """Axis-aligned box of size (sx, sy, sz) whose bottom face is centred at (x, y, z)."""
    return creation.box(extents=(sx, sy, sz), transform=tf.translation_matrix((x, y, z + sz / 2)))


def cylinder(r: float, z0: float, z1: float, x: float = 0.0, y: float = 0.0, sections: int = 16) -> trimesh.Trimesh:
    """Vertical cylinder from z0 to z1 around (x, y)."""
    return rod((x, y, z0), (x, y, z1), r, sections)


def rod(p0: Vec, p1: Vec, r: float, sections: int = 8) -> trimesh.Trimesh:
    """Cylinder of radius r between two points."""
    return creation.cylinder(radius=r, segment=np.array([p0, p1], float), sections=sections)


def lathe(profile: Sequence[Vec], x: float = 0.0, y: float = 0.0, sections: int = 16) -> trimesh.Trimesh:
    """Solid of revolution about the vertical line through (x, y); profile is [(r, z), ...] from the
    axis back to the axis."""
    mesh = creation.revolve(np.asarray(profile, float), sections=sections)
    if mesh.volume < 0:
        mesh.invert()
    return mesh.apply_translation((x, y, 0.0))


def frustum(r0: float, r1: float, z0: float, z1: float, x: float = 0.0, y: float = 0.0,
            sections: int = 16) -> trimesh.Trimesh:
    """Truncated cone: radius r0 at z0, r1 at z1 (r1 may be 0 for a cone)."""
    return lathe([(0.0, z0), (r0, z0), (r1, z1), (0.0, z1)] if r1 > 0 else [(0.0, z0), (r0, z0), (0.0, z1)],
                 x, y, sections)


def sphere(r: float, centre: Vec = (0.0, 0.0, 0.0), sub: int = 1, scale: Vec = (1.0, 1.0, 1.0)) -> trimesh.Trimesh:
    """Icosphere of radius r, optionally scaled per axis into an ellipsoid, centred at `centre`."""
    mesh = creation.icosphere(subdivisions=sub, radius=r)
    mesh.apply_scale(np.asarray(scale, float))
    return mesh.apply_translation(centre)


def torus(major: float, minor: float, centre: Vec = (0.0, 0.0, 0.0), sections: int = 20,
          minor_sections: int = 8) -> trimesh.Trimesh:
    """Horizontal torus (ring in the xy plane) centred at `centre`."""
    mesh = creation.torus(major_radius=major, minor_radius=minor, major_sections=sections,
                          minor_sections=minor_sections)
    return mesh.apply_translation(centre)


def ring(r_in: float, r_out: float, z0: float, z1: float, sections: int = 20) -> trimesh.Trimesh:
    """Vertical tube wall (annulus) around the z axis from z0 to z1."""
    mesh = creation.annulus(r_min=r_in, r_max=r_out, height=z1 - z0, sections=sections)
    return mesh.apply_translation((0.0, 0.0, (z0 + z1) / 2))


def regular_polygon(n: int, r: float, phase_deg: float = 0.0, centre: Vec = (0.0, 0.0)) -> np.ndarray:
    """n vertices (counter-clockwise) on a circle of radius r."""
    a = np.radians(phase_deg) + np.arange(n) * 2 * np.pi / n
    return np.column_stack([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a)])


def star_polygon(points: int, r_out: float, r_in: float, phase_deg: float = 90.0,
                 centre: Vec = (0.0, 0.0)) -> np.ndarray:
    """Star with `points` tips (also used for the fluting of a column)."""
    radii = np.where(np.arange(2 * points) % 2 == 0, r_out, r_in)
    a = np.radians(phase_deg) + np.arange(2 * points) * np.pi / points
    return np.column_stack([centre[0] + radii * np.cos(a), centre[1] + radii * np.sin(a)])


def rect(sx: float, sy: float, cx: float = 0.0, cy: float = 0.0) -> np.ndarray:
    return np.array([(cx - sx / 2, cy - sy / 2), (cx + sx / 2, cy - sy / 2), (cx + sx / 2, cy + sy / 2),
                     (cx - sx / 2, cy + sy / 2)])


def _signed_area(poly: np.ndarray) -> float:
    return 0.5 * float(np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1]))


def loft(poly0: Sequence[Vec], z0: float, poly1: Sequence[Vec], z1: float) -> trimesh.Trimesh:
    """Closed solid between two horizontal polygons with the same vertex count (z0 < z1).

    The caps are fanned from the vertex mean, so each polygon must be star-shaped about it."""
    a, b = np.asarray(poly0, float), np.asarray(poly1, float)
    if _signed_area(a) < 0:
        a, b = a[::-1], b[::-1]
    n = len(a)
    vertices = np.vstack([np.column_stack([a, np.full(n, z0)]), np.column_stack([b, np.full(n, z1)]),
                          [[*a.mean(axis=0), z0], [*b.mean(axis=0), z1]]])
    i = np.arange(n)
    j = (i + 1) % n
    faces = np.vstack([np.column_stack([i, j, n + j]), np.column_stack([i, n + j, n + i]),
                       np.column_stack([np.full(n, 2 * n), j, i]),
                       np.column_stack([np.full(n, 2 * n + 1), n + i, n + j])])
    return _mesh(vertices, faces)


def prism(poly: Sequence[Vec], z0: float, z1: float) -> trimesh.Trimesh:
    """Vertical extrusion of a star-shaped polygon."""
    return loft(poly, z0, poly, z1)


def extrude_x(profile: Sequence[Vec], x0: float, x1: float) -> trimesh.Trimesh:
    """Extrude a profile given in (y, z) along x from x0 to x1."""
    mesh = prism(profile, x0, x1)
    return mesh.apply_transform(np.array([[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float))


def extrude_y(profile: Sequence[Vec], y0: float, y1: float) -> trimesh.Trimesh:
    """Extrude a profile given in (x, z) along y from y0 to y1."""
    mesh = prism(profile, -y1, -y0)
    return mesh.apply_transform(np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float))


def slab(p0: Vec, p1: Vec, width: float, thick: float, normal: Vec = (0.0, 0.0, 1.0)) -> trimesh.Trimesh:
    """Plank from p0 to p1; its thickness lies along `normal` (made perpendicular to the plank) and its
    width along the remaining direction."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    length = float(np.linalg.norm(d))
    ax = d / length
    n = np.asarray(normal, float)
    az = n - np.dot(n, ax) * ax
    az /= np.linalg.norm(az)
    frame = np.eye(4)
    frame[:3, 0], frame[:3, 1], frame[:3, 2], frame[:3, 3] = ax, np.cross(az, ax), az, (p0 + p1) / 2
    return creation.box(extents=(length, width, thick), transform=frame)


def half_disc(r: float, segments: int = 8, centre: Vec = (0.0, 0.0)) -> np.ndarray:
    """Upper half of a disc as a polygon (for arches, vaults and tunnels)."""
    a = np.linspace(0.0, np.pi, segments + 1)
    return np.column_stack([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a)])


def rock(rng: np.random.Generator, r: float, at: Vec = (0.0, 0.0), scale: Vec = (1.0, 1.0, 1.0),
         amp: float = 0.18, sub: int = 1, floor: float = -0.4, lift: float = 0.0) -> trimesh.Trimesh:
    """Jittered icosphere with a flattened underside, resting on z = lift at (x, y) = at."""
    base = creation.icosphere(subdivisions=sub, radius=1.0)
    v = base.vertices * (1.0 + amp * rng.uniform(-1.0, 1.0, (len(base.vertices), 1)))
    v[:, 2] = np.maximum(v[:, 2], floor)
    v = v * r * np.asarray(scale, float)
    v += (at[0], at[1], lift - floor * r * scale[2])
    return _mesh(v, base.faces)


def arc_points(n: int, radius: float, centre: Vec, z: float, phase_deg: float = 0.0) -> list[tuple[float, ...]]:
    """n points evenly spaced on a horizontal circle."""
    xy = regular_polygon(n, radius, phase_deg, centre[:2])
    return [(float(px), float(py), z) for px, py in xy]


# --------------------------------------------------------------------------------------------------
# Part collection and normalisation.
# --------------------------------------------------------------------------------------------------


class Parts:
    """Collects meshes per colour; `build` merges each colour into one part and normalises the model
    (footprint bounding box centred on x = y = 0, lowest point on z = 0, coordinates rounded to 10 um)."""

    def __init__(self) -> None:
        self._groups: dict[str, list[trimesh.Trimesh]] = {}

    def add(self, colour: str, *meshes: trimesh.Trimesh) -> None:
        self._groups.setdefault(colour, []).extend(meshes)

    def build(self) -> list[LandmarkPart]:
        merged = [(c, trimesh.util.concatenate(ms)) for c, ms in self._groups.items()]
        lo = np.min([m.bounds[0] for _, m in merged], axis=0)
        hi = np.max([m.bounds[1] for _, m in merged], axis=0)
        shift = np.array([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
        parts = []
        for colour, mesh in merged:
            v = np.round(mesh.vertices + shift, 5) + 0.0  # + 0.0 turns -0.0 into 0.0
            tri = v[mesh.faces]
            keep = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) > 1e-10
            parts.append(LandmarkPart(_mesh(v, mesh.faces[keep]), hex_rgba(colour)))
        return parts


_BUILDERS: dict[str, Callable[[Parts], None]] = {}


def _run(builder: Callable[[Parts], None]) -> list[LandmarkPart]:
    parts = Parts()
    builder(parts)
    return parts.build()


def landmark(name: str) -> Callable[[Callable[[Parts], None]], Callable[[Parts], None]]:
    """Register a builder as the mesh of the catalogue entry `name` (gsmn.world.catalogue)."""

    def register(builder: Callable[[Parts], None]) -> Callable[[Parts], None]:
        if name in _BUILDERS:
            raise ValueError(f"landmark {name!r} has two builders")
        _BUILDERS[name] = builder
        return builder

    return register


# --------------------------------------------------------------------------------------------------
# Recurring compound shapes.
# --------------------------------------------------------------------------------------------------


def tiered_crown(tiers: Iterable[tuple[float, float, float]], sections: int = 14) -> list[trimesh.Trimesh]:
    """Stacked cones (radius, bottom z, height) of a conifer."""
    return [frustum(r, 0.0, z0, z0 + h, sections=sections) for r, z0, h in tiers]


def ornaments(tiers: Sequence[tuple[float, float, float]], fractions: Sequence[float], per_ring: int,
              size: float) -> list[tuple[float, float, float]]:
    """Points on the surfaces of conical tiers (for baubles)."""
    points = []
    for t, (r, z0, h) in enumerate(tiers):
        for f_i, f in enumerate(fractions):
            ring = r * (1 - f) + size * 0.6
            for px, py, pz in arc_points(per_ring, ring, (0, 0), z0 + f * h, 37.0 * t + 30.0 * f_i):
                points.append((px, py, pz))
    return points


def frond(base: Vec, yaw_deg: float, length: float, width: float, lift: float, sag: float,
          segments: int = 4) -> list[trimesh.Trimesh]:
    """Palm frond: flat slabs along the drooping arc z = lift * d - sag * d^2 / length."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    pts = []
    for k in range(segments + 1):
        d = length * k / segments
        pts.append((base[0] + c * d, base[1] + s * d, base[2] + lift * d - sag * d * d / length))
    return [slab(pts[k], pts[k + 1], width * (1.0 - 0.55 * k / segments), 0.06) for k in range(segments)]


def palm(p: Parts, trunk: np.ndarray, *, radii: tuple[float, float], crown: str, fronds: int, length: float,
         width: float, lift: float, sag: float, yaw0: float = 0.0, fruit: str | None = None) -> None:
    """Palm tree: a ringed trunk along the polyline `trunk` (radius tapering from radii[0] to radii[1])
    and a crown of `fronds` drooping fronds (see `frond`), optionally with fruit under the crown."""
    r_base, r_top = radii
    n = len(trunk) - 1
    for k in range(n):
        r = r_base + (r_top - r_base) * k / max(n - 1, 1)
        colour = PALM_BARK if k % 2 == 0 else PALM_BARK_DARK
        p.add(colour, rod(trunk[k], trunk[k + 1], r, 10))
        if k:
            p.add(colour, sphere(r, trunk[k], sub=1))
    top = trunk[-1]
    p.add(crown, sphere(r_top * 1.5, top, sub=1))
    for i in range(fronds):
        p.add(crown, *frond(top, yaw0 + 360.0 * i / fronds, length, width, lift, sag))
    if fruit is not None:
        p.add(fruit, *[sphere(0.17, pt, sub=1) for pt in arc_points(3, r_top + 0.12, top, top[2] - 0.28, yaw0)])


def blob_cluster(rng: np.random.Generator, blobs: Sequence[tuple[float, float, float, float]],
                 jitter: float = 0.08) -> list[trimesh.Trimesh]:
    """Foliage: jittered spheres (x, y, z, r)."""
    out = []
    for x, y, z, r in blobs:
        base = creation.icosphere(subdivisions=1, radius=r)
        v = base.vertices * (1.0 + jitter * rng.uniform(-1.0, 1.0, (len(base.vertices), 1))) + (x, y, z)
        out.append(_mesh(v, base.faces))
    return out


def dots_on(rng: np.random.Generator, blobs: Sequence[tuple[float, float, float, float]], count: int,
            size: float) -> list[trimesh.Trimesh]:
    """Small spheres (flowers, berries) scattered over the upper surfaces of foliage blobs."""
    out = []
    for _ in range(count):
        x, y, z, r = blobs[int(rng.integers(len(blobs)))]
        d = rng.normal(size=3)
        d[2] = abs(d[2]) * 0.8 + 0.1
        d /= np.linalg.norm(d)
        out.append(sphere(size, (x + d[0] * r * 1.03, y + d[1] * r * 1.03, z + d[2] * r * 1.03), sub=0))
    return out


def panel(side: str, half_x: float, half_y: float, u: float, z0: float, width: float, height: float,
          proud: float = 0.05) -> trimesh.Trimesh:
    """Thin box on a face of a wall block of half-size (half_x, half_y): side is 'front' (-y), 'back'
    (+y), 'left' (-x) or 'right' (+x); u is the offset along the wall."""
    t = 2 * proud
    if side in ("front", "back"):
        return block(width, t, height, u, -half_y if side == "front" else half_y, z0)
    return block(t, width, height, -half_x if side == "left" else half_x, u, z0)


def gable_roof(p: Parts, roof: str, gable: str, w: float, d: float, z: float, rise: float, overhang: float,
               thick: float = 0.14) -> None:
    """Gable roof with the ridge along x over a w x d wall block whose top is at height z."""
    p.add(gable, extrude_x([(-d / 2, z), (d / 2, z), (0.0, z + rise)], -w / 2, w / 2))
    slope = rise / (d / 2)
    for sgn in (-1.0, 1.0):
        run = d / 2 + overhang
        direction = np.array([0.0, sgn * run, -slope * run]) / math.hypot(run, slope * run)
        up = np.array([0.0, sgn * slope, 1.0]) / math.hypot(slope, 1.0)
        ridge = np.array([0.0, 0.0, z + rise]) + up * thick / 2
        eave = ridge + direction * math.hypot(run, slope * run)
        p.add(roof, slab(ridge - direction * thick, eave, w + 2 * overhang, thick, normal=up))
    p.add(roof, rod((-w / 2 - overhang, 0, z + rise + thick * 0.6), (w / 2 + overhang, 0, z + rise + thick * 0.6),
                    thick * 0.7, 8))


def windows(side: str, half_x: float, half_y: float, us: Iterable[float], zs: Iterable[float],
            size: tuple[float, float]) -> list[trimesh.Trimesh]:
    """A grid of window panels on one wall face."""
    return [panel(side, half_x, half_y, u, z, size[0], size[1]) for u in us for z in zs]


def barrel_body(r: float, h: float, bulge: float = 0.0, sections: int = 20) -> trimesh.Trimesh:
    """Upright barrel body (z from 0 to h) whose radius bulges by `bulge` * r at mid-height."""
    zs = np.linspace(0.0, h, 7)
    profile = [(0.0, 0.0)] + [(r * (1 - bulge * (2 * z / h - 1) ** 2), z) for z in zs] + [(0.0, h)]
    return lathe(profile, sections=sections)


def hoops(r: float, h: float, bulge: float, at: Iterable[float], width: float, proud: float = 0.035,
          sections: int = 20) -> list[trimesh.Trimesh]:
    """Bands around a barrel body at heights `at` (band centres)."""
    out = []
    for z in at:
        rz = r * (1 - bulge * (2 * z / h - 1) ** 2) + proud
        out.append(cylinder(rz, z - width / 2, z + width / 2, sections=sections))
    return out


def mushroom(p: Parts, x: float, y: float, stem_r: float, stem_h: float, cap_r: float, cap_h: float, cap: str,
             stem: str) -> tuple[float, float]:
    """Stem plus domed cap; returns (cap base z, cap height) for decorating the cap."""
    p.add(stem, frustum(stem_r * 1.25, stem_r, 0.0, stem_h, x, y))
    z0 = stem_h - 0.1 * cap_h
    profile = [(0.0, z0), (cap_r, z0), (cap_r * 1.0, z0 + 0.18 * cap_h), (cap_r * 0.82, z0 + 0.6 * cap_h),
               (cap_r * 0.45, z0 + 0.92 * cap_h), (0.0, z0 + cap_h)]
    p.add(cap, lathe(profile, x, y, sections=20))
    return z0, cap_h


def seven_segment(letter: str, x: float, z: float, w: float, h: float, stroke: float, y: float,
                  depth: float = 0.03) -> list[trimesh.Trimesh]:
    """Block letter in seven-segment style on the plane y (for the stop sign), lower-left at (x, z)."""
    hor = {"a": h - stroke, "g": (h - stroke) / 2, "d": 0.0}
    ver = {"f": (0.0, h / 2), "b": (w - stroke, h / 2), "e": (0.0, 0.0), "c": (w - stroke, 0.0)}
    segments = {"S": "afgcd", "O": "abcdef", "P": "abfge", "T": "a"}[letter]
    out = []
    for s in segments:
        if s in hor:
            out.append(block(w, depth, stroke, x + w / 2, y, z + hor[s]))
        else:
            du, dz = ver[s]
            out.append(block(stroke, depth, h / 2, x + du + stroke / 2, y, z + dz))
    if letter == "T":
        out.append(block(stroke, depth, h - stroke, x + w / 2, y, z))
    return out


# ==================================================================================================
# The catalogue.  Registration order below is the class id.
# ==================================================================================================

# ---- trees and plants ------------------------------------------------------------------------------


@landmark("fir_tree")
def _fir_tree(p: Parts) -> None:
    p.add(BARK, cylinder(0.28, 0.0, 1.3, sections=10))
    p.add("#1d5a2c", *tiered_crown([(2.1, 0.9, 2.4), (1.7, 2.2, 2.1), (1.3, 3.4, 1.9), (0.9, 4.6, 1.7)]))


_XMAS_TIERS = [(2.0, 0.8, 2.2), (1.55, 2.3, 1.9), (1.1, 3.5, 1.7)]


@landmark("christmas_tree_1")
def _christmas_tree_1(p: Parts) -> None:
    p.add(BARK, cylinder(0.25, 0.0, 1.0, sections=10))
    p.add("#2e8b3a", *tiered_crown(_XMAS_TIERS, sections=16))
    colours = (RED, GOLD, BLUE)
    for i, pt in enumerate(ornaments(_XMAS_TIERS, (0.2, 0.55), 6, 0.16)):
        p.add(colours[i % 3], sphere(0.16, pt, sub=0))
    top = _XMAS_TIERS[-1][1] + _XMAS_TIERS[-1][2]
    p.add(GOLD, extrude_y(star_polygon(5, 0.45, 0.2, centre=(0.0, top + 0.25)), -0.08, 0.08))
    p.add(RED, block(0.6, 0.6, 0.5, 1.0, -0.9, 0.0))
    p.add(BLUE, block(0.5, 0.5, 0.4, -1.1, -0.7, 0.0))


@landmark("christmas_tree_2")
def _christmas_tree_2(p: Parts) -> None:
    p.add(RED, frustum(0.5, 0.7, 0.0, 0.7))
    p.add("#17805a", frustum(1.45, 0.0, 0.6, 5.0, sections=16))
    lights = []
    for k in range(34):
        t = k / 34
        z = 0.85 + t * 3.7
        r = 1.45 * (1 - (z - 0.6) / 4.4) + 0.06
        a = t * 4.5 * 2 * math.pi
        lights.append(sphere(0.1, (r * math.cos(a), r * math.sin(a), z), sub=0))
    p.add("#fff27a", *lights[0::2])
    p.add(WHITE, *lights[1::2])
    p.add(RED, extrude_y(star_polygon(5, 0.42, 0.18, centre=(0.0, 5.2)), -0.07, 0.07))


def _trunk_line(n: int, top: Vec, bend: float = 1.0, base_z: float = 0.0) -> np.ndarray:
    """n points from (0, 0, base_z) to `top`; the horizontal offset grows as t**bend (1 = straight)."""
    t = np.linspace(0.0, 1.0, n)
    return np.column_stack([top[0] * t**bend, top[1] * t**bend, base_z + (top[2] - base_z) * t])


@landmark("palm_tree_1")
def _palm_tree_1(p: Parts) -> None:  # tall and straight, with coconuts
    palm(p, _trunk_line(8, (0.0, 0.0, 6.3)), radii=(0.3, 0.2), crown="#2e9e3e", fronds=9, length=2.5, width=0.5,
         lift=0.5, sag=1.1, fruit=WOOD_DARK)


@landmark("palm_tree_2")
def _palm_tree_2(p: Parts) -> None:  # curved, leaning trunk
    palm(p, _trunk_line(8, (1.5, 0.2, 6.0), bend=2.0), radii=(0.28, 0.18), crown="#1f7a36", fronds=7, length=2.3,
         width=0.55, lift=0.6, sag=1.3, yaw0=15.0, fruit=WOOD_DARK)


@landmark("palm_tree_3")
def _palm_tree_3(p: Parts) -> None:  # twin trunks from one root mound, light green
    p.add(WOOD, frustum(0.75, 0.45, 0.0, 0.4))
    for top, yaw0 in (((-0.9, 0.1, 5.6), 0.0), ((0.95, -0.1, 4.5), 22.0)):
        palm(p, _trunk_line(7, top, bend=1.5, base_z=0.2), radii=(0.24, 0.17), crown="#6cc03a", fronds=8,
             length=1.7, width=0.42, lift=0.6, sag=1.2, yaw0=yaw0)


@landmark("palm_tree_4")
def _palm_tree_4(p: Parts) -> None:  # short, thick date palm with a dense crown and orange dates
    palm(p, _trunk_line(7, (0.0, 0.0, 3.0)), radii=(0.5, 0.38), crown="#4b9a26", fronds=14, length=2.05,
         width=0.45, lift=1.0, sag=1.25, fruit=ORANGE)


_BUSH_1 = [(0.0, 0.0, 0.95, 1.0), (0.75, 0.2, 0.7, 0.7), (-0.7, 0.35, 0.7, 0.72), (0.1, -0.75, 0.7, 0.7),
           (-0.35, -0.5, 0.75, 0.6), (0.1, 0.1, 1.65, 0.65)]
_BUSH_2 = [(-1.1, 0.0, 0.7, 0.8), (0.0, 0.0, 0.85, 1.0), (1.1, 0.1, 0.7, 0.8), (-0.5, 0.6, 0.6, 0.6),
           (0.5, -0.6, 0.6, 0.6), (0.2, 0.1, 1.4, 0.6)]
_BUSH_3 = [(0.0, 0.0, 1.0, 1.1), (0.0, 0.0, 2.0, 0.9), (0.9, 0.3, 0.9, 0.8), (-0.9, -0.2, 0.9, 0.85),
           (0.3, -0.9, 0.8, 0.75), (-0.4, 0.9, 0.8, 0.75), (0.2, 0.2, 2.7, 0.6)]


@landmark("bush_1")
def _bush_1(p: Parts) -> None:
    p.add("#3fb03c", *blob_cluster(np.random.default_rng(101), _BUSH_1))


@landmark("bush_2")
def _bush_2(p: Parts) -> None:
    rng = np.random.default_rng(102)
    p.add("#2d8c3c", *blob_cluster(rng, _BUSH_2))
    p.add(PINK, *dots_on(rng, _BUSH_2, 22, 0.13))


@landmark("bush_3")
def _bush_3(p: Parts) -> None:
    rng = np.random.default_rng(103)
    p.add("#1e6a34", *blob_cluster(rng, _BUSH_3))
    p.add(RED, *dots_on(rng, _BUSH_3, 24, 0.11))


@landmark("cactus")
def _cactus(p: Parts) -> None:
    green = "#239a58"
    p.add(SAND, frustum(1.0, 0.75, 0.0, 0.25))
    p.add(green, creation.capsule(height=3.2, radius=0.38, count=[12, 12]).apply_translation((0, 0, 2.18)))
    for x, z, top in ((1.05, 1.7, 2.9), (-0.95, 2.3, 3.3)):
        p.add(green, rod((0, 0, z), (x, 0, z), 0.26, 10), sphere(0.26, (x, 0, z)),
              creation.capsule(height=top - z, radius=0.26, count=[10, 10]).apply_translation((x, 0, (top + z) / 2)))
        p.add(PINK, sphere(0.14, (x, 0, top + 0.25)))
    p.add(PINK, sphere(0.16, (0, 0, 4.1)))


@landmark("mushroom_1")
def _mushroom_1(p: Parts) -> None:
    z0, h = mushroom(p, 0.0, 0.0, 0.32, 1.3, 1.15, 0.85, RED, "#f3ead2")
    p.add("#f3ead2", frustum(0.3, 0.48, 0.95, 1.08))
    spots = [(0.0, 0.0)] + [(0.5, a) for a in range(0, 360, 72)] + [(0.92, a + 25) for a in range(0, 360, 51)]
    for rho, a in spots:
        z = z0 + h * math.sqrt(max(0.0, 1 - (rho / 1.18) ** 2))
        x, y = rho * math.cos(math.radians(a)), rho * math.sin(math.radians(a))
        p.add(WHITE, sphere(0.14, (x, y, z), scale=(1, 1, 0.55)))


@landmark("mushroom_2")
def _mushroom_2(p: Parts) -> None:
    for x, y, sr, sh, cr, ch in ((0.0, 0.0, 0.36, 1.2, 1.0, 0.75), (1.05, 0.35, 0.16, 0.55, 0.45, 0.35),
                                 (-0.95, -0.45, 0.19, 0.7, 0.52, 0.4)):
        mushroom(p, x, y, sr, sh, cr, ch, "#7b4a22", "#ece0c0")


@landmark("pumpkin")
def _pumpkin(p: Parts) -> None:
    angles = np.radians(np.linspace(-80.0, 80.0, 9))
    profile = [(0.0, 0.08)] + [(math.cos(a), 0.66 + 0.6 * math.sin(a)) for a in angles] + [(0.0, 1.14)]
    body = lathe(profile, sections=40)
    lobes = lambda phi: 1.0 + 0.07 * np.cos(10 * phi)
    phi = np.arctan2(body.vertices[:, 1], body.vertices[:, 0])
    body.vertices[:, :2] *= lobes(phi)[:, None]
    p.add(ORANGE, body)
    p.add("#4d6b1f", rod((0, 0, 1.0), (0.08, 0.05, 1.5), 0.1, 8))
    # Jack-o'-lantern face: prisms whose front vertices are pulled onto the lobed surface.
    eyes = [[(-0.5, 0.72), (-0.15, 0.72), (-0.32, 0.98)], [(0.15, 0.72), (0.5, 0.72), (0.32, 0.98)]]
    mouth = [(-0.55, 0.5), (-0.3, 0.3), (0.3, 0.3), (0.55, 0.5), (0.0, 0.42)]
    for shape in (*eyes, mouth):
        feature = extrude_y(shape, -1.2, -0.5)
        v = feature.vertices
        front = v[:, 1] < -1.1
        x, z = v[front, 0], v[front, 2]
        ring = np.sqrt(np.clip(1.0 - ((z - 0.66) / 0.6) ** 2, 0.0, 1.0))
        angle = np.arctan2(-ring, x)
        for _ in range(6):
            angle = np.arctan2(-np.sqrt(np.maximum((ring * lobes(angle)) ** 2 - x**2, 0.0)), x)
        v[front, 1] = -np.sqrt(np.maximum((ring * lobes(angle)) ** 2 - x**2, 0.0)) - 0.04
        p.add(BLACK, _mesh(v, feature.faces))


# ---- rocks ------------------------------------------------------------------------------------------


@landmark("rock_1")
def _rock_1(p: Parts) -> None:
    rng = np.random.default_rng(11)
    p.add("#8a8d91", rock(rng, 1.3, (0, 0), (1.2, 1.0, 0.95)), rock(rng, 0.45, (1.3, 0.7), (1.0, 0.9, 0.8)))


@landmark("rock_2")
def _rock_2(p: Parts) -> None:
    rng = np.random.default_rng(12)
    p.add("#c9803f", rock(rng, 2.0, (0, 0), (1.0, 0.8, 0.32), amp=0.12))
    p.add("#e0a35e", rock(rng, 1.3, (0.3, -0.1), (1.0, 0.85, 0.4), amp=0.14, lift=0.35))


@landmark("rock_3")
def _rock_3(p: Parts) -> None:
    rng = np.random.default_rng(13)
    p.add("#4f5a66", rock(rng, 0.9, (0, 0), (1.0, 0.85, 2.3), amp=0.2, floor=-0.5),
          rock(rng, 0.6, (0.95, 0.4), (1.0, 0.8, 1.5), amp=0.2))


@landmark("rock_4")
def _rock_4(p: Parts) -> None:
    rng = np.random.default_rng(14)
    p.add("#9a4b2c", rock(rng, 1.25, (0, 0), (1.1, 1.0, 0.9)), rock(rng, 0.9, (1.45, 0.5), (1.0, 1.0, 0.85)),
          rock(rng, 0.7, (-1.1, 1.05), (1.0, 0.9, 0.9)))


@landmark("stone_circle")
def _stone_circle(p: Parts) -> None:
    rng = np.random.default_rng(15)
    stones = []
    for k in range(8):
        a = 22.5 + 45.0 * k
        stone = place(block(0.55, 0.4, 1.9), rx=float(rng.uniform(-4, 4)), ry=float(rng.uniform(-4, 4)))
        stones.append(place(stone, (2.1 * math.cos(math.radians(a)), 2.1 * math.sin(math.radians(a)), 0.0),
                            rz=a + 90.0))
    for k in (0, 3, 6):
        a = 45.0 * (k + 1)
        r = 2.1 * math.cos(math.radians(22.5))
        at = (r * math.cos(math.radians(a)), r * math.sin(math.radians(a)), 1.86)
        stones.append(place(block(2.0, 0.42, 0.32), at, rz=a + 90.0))
    p.add("#85878a", *stones)
    p.add("#6b6259", block(1.1, 0.7, 0.55))


# ---- buildings ----------------------------------------------------------------------------------------


@landmark("house_1")
def _house_1(p: Parts) -> None:
    w, d, h = 3.8, 3.0, 2.6
    p.add("#f2efe6", block(w, d, h))
    gable_roof(p, "#c0392b", "#f2efe6", w, d, h, 1.5, 0.25)
    p.add("#8e3b2a", block(0.45, 0.45, 1.7, 1.1, 0.5, 3.0))
    p.add("#6b3d1f", panel("front", w / 2, d / 2, -0.9, 0.0, 0.8, 1.7))
    p.add("#4a90d9", *windows("front", w / 2, d / 2, (0.8,), (1.1,), (0.8, 0.8)),
          *windows("back", w / 2, d / 2, (-0.9, 0.9), (1.1,), (0.8, 0.8)),
          *windows("left", w / 2, d / 2, (0.0,), (1.1,), (0.8, 0.8)),
          *windows("right", w / 2, d / 2, (0.0,), (1.1,), (0.8, 0.8)))


@landmark("house_2")
def _house_2(p: Parts) -> None:
    w, d, h = 3.6, 3.0, 4.6
    p.add("#7fb3e0", block(w, d, h))
    p.add("#3f4452", loft(rect(w + 0.6, d + 0.6), h, rect(w - d + 0.2, 0.12), h + 1.4))
    p.add("#b22222", panel("front", w / 2, d / 2, 0.0, 0.0, 0.8, 1.8))
    navy = "#1f3a5f"
    p.add(navy, *windows("front", w / 2, d / 2, (-1.1, 1.1), (0.9,), (0.7, 0.9)),
          *windows("front", w / 2, d / 2, (-1.1, 0.0, 1.1), (3.0,), (0.7, 0.9)),
          *windows("back", w / 2, d / 2, (-0.9, 0.9), (0.9, 3.0), (0.7, 0.9)),
          *windows("left", w / 2, d / 2, (0.0,), (0.9, 3.0), (0.7, 0.9)),
          *windows("right", w / 2, d / 2, (0.0,), (0.9, 3.0), (0.7, 0.9)))
    p.add(WHITE, block(w + 0.04, d + 0.04, 0.15, z=2.25))


@landmark("house_3")
def _house_3(p: Parts) -> None:
    w, d, h = 3.2, 3.2, 2.5
    p.add("#f2c94c", block(w, d, h))
    p.add("#b5532a", loft(rect(w + 0.5, d + 0.5), h, rect(0.12, 0.12), h + 1.8))
    p.add("#b5532a", block(1.6, 0.75, 0.12, 0, -d / 2 - 0.3, 2.1))
    p.add(WHITE, *[cylinder(0.07, 0.0, 2.1, x, -d / 2 - 0.55, 8) for x in (-0.7, 0.7)])
    p.add("#2e7d32", panel("front", w / 2, d / 2, 0.0, 0.0, 0.75, 1.7))
    p.add(SKY, *windows("front", w / 2, d / 2, (-1.05, 1.05), (1.0,), (0.6, 0.7)),
          *windows("back", w / 2, d / 2, (-0.8, 0.8), (1.0,), (0.6, 0.7)),
          *windows("left", w / 2, d / 2, (-0.6, 0.6), (1.0,), (0.6, 0.7)),
          *windows("right", w / 2, d / 2, (-0.6, 0.6), (1.0,), (0.6, 0.7)))


@landmark("wooden_house")
def _wooden_house(p: Parts) -> None:
    w, d, r, rows = 3.7, 3.0, 0.16, 8
    h = 2 * r * rows
    p.add("#6e4420", block(w - 0.1, d - 0.1, h))
    for k in range(rows):
        colour = "#9a6234" if k % 2 == 0 else "#84522a"
        z = r + 2 * r * k
        p.add(colour, *[rod((-w / 2 - 0.25, y, z), (w / 2 + 0.25, y, z), r, 8) for y in (-d / 2, d / 2)])
        p.add(colour, *[rod((x, -d / 2 - 0.25, z + r), (x, d / 2 + 0.25, z + r), r, 8) for x in (-w / 2, w / 2)])
    gable_roof(p, "#2f6e4e", "#9a6234", w, d, h + r, 1.4, 0.3)
    p.add(WOOD_DARK, panel("front", w / 2, d / 2, 0.6, 0.0, 0.8, 1.8, proud=0.22))
    p.add("#f2d36b", panel("front", w / 2, d / 2, -0.9, 1.0, 0.8, 0.7, proud=0.22),
          *windows("left", w / 2, d / 2, (0.0,), (1.0,), (0.7, 0.7)), *windows("right", w / 2, d / 2, (0.0,), (1.0,),
                                                                                  (0.7, 0.7)))
    p.add(GREY, block(0.5, 0.5, 1.8, -1.2, 0.45, 3.0))


@landmark("tower_1")
def _tower_1(p: Parts) -> None:
    stone = "#9b9b9b"
    p.add(stone, frustum(1.65, 1.4, 0.0, 0.6, sections=20), cylinder(1.4, 0.5, 5.6, sections=20),
          frustum(1.4, 1.65, 5.6, 6.0, sections=20), cylinder(1.65, 6.0, 6.15, sections=20))
    p.add(stone, *[place(block(0.5, 0.35, 0.6, 0.0, -1.47, 6.1), rz=a) for a in range(0, 360, 36)])
    p.add(BLACK, panel("front", 1.4, 1.4, 0.0, 0.0, 0.9, 1.8, proud=0.1),
          *[place(block(0.2, 0.2, 0.8, 0.0, -1.4, z), rz=phase + a) for z, phase in ((2.6, 45.0), (4.2, 0.0))
            for a in (0, 90, 180, 270)])
    p.add(DARK_GREY, cylinder(0.05, 6.1, 7.7, sections=6))
    p.add(RED, block(0.8, 0.05, 0.5, 0.42, 0.0, 7.15))


@landmark("tower_2")
def _tower_2(p: Parts) -> None:
    cream = "#e6d5b0"
    p.add(cream, block(2.3, 2.3, 0.6), block(2.0, 2.0, 5.4), block(2.3, 2.3, 0.25, z=5.2), block(2.1, 2.1, 1.4, z=5.45))
    p.add("#3c9f84", loft(rect(2.4, 2.4), 6.85, rect(0.1, 0.1), 7.95))
    p.add(DARK_GREY, *windows("front", 1.0, 1.0, (0.0,), (1.4, 3.2), (0.5, 1.0)),
          *windows("back", 1.0, 1.0, (0.0,), (1.4, 3.2), (0.5, 1.0)),
          *windows("left", 1.0, 1.0, (0.0,), (1.4, 3.2), (0.5, 1.0)),
          *windows("right", 1.0, 1.0, (0.0,), (1.4, 3.2), (0.5, 1.0)))
    for a in (0.0, 90.0, 180.0, 270.0):
        p.add(WHITE, place(rod((0, -1.05, 0), (0, -1.12, 0), 0.55, 20), (0, 0, 6.15), rz=a))
        p.add(BLACK, place(block(0.07, 0.04, 0.42, 0, -1.13, -0.02), (0, 0, 6.15), rz=a),
              place(block(0.34, 0.04, 0.07, 0.15, -1.13, -0.03), (0, 0, 6.15), rz=a))


@landmark("lighthouse")
def _lighthouse(p: Parts) -> None:
    p.add(GREY, frustum(1.3, 1.2, 0.0, 0.5, sections=8))
    zs = np.linspace(0.5, 6.1, 6)
    radius = lambda z: 1.0 - 0.35 * (z - 0.5) / 5.6
    for k in range(5):
        p.add(RED if k % 2 == 0 else WHITE, frustum(radius(zs[k]), radius(zs[k + 1]), zs[k], zs[k + 1], sections=20))
    p.add(BLACK, cylinder(0.95, 6.1, 6.25, sections=20), cylinder(0.6, 6.25, 6.35, sections=16))
    p.add("#ffe680", cylinder(0.55, 6.3, 7.05, sections=16))
    p.add(RED, lathe([(0.0, 7.05), (0.7, 7.05), (0.45, 7.4), (0.0, 7.6)], sections=16))
    p.add(BLACK, panel("front", 1.0, 0.98, 0.0, 0.5, 0.6, 1.2, proud=0.08))


@landmark("windmill")
def _windmill(p: Parts) -> None:
    p.add(WHITE, frustum(1.6, 1.0, 0.0, 4.8, sections=8))
    p.add("#b33a2e", lathe([(0.0, 4.75), (1.15, 4.75), (1.05, 5.3), (0.6, 5.8), (0.0, 5.95)], sections=12))
    p.add(WOOD_DARK, panel("front", 1.5, 1.5, 0.0, 0.0, 0.8, 1.6, proud=0.12))
    hub = np.array([0.0, -1.3, 5.2])
    p.add(DARK_GREY, rod((0, 0, 5.2), hub - (0, 0.1, 0), 0.16, 10))
    for k in range(4):
        a = math.radians(45.0 + 90.0 * k)
        u = np.array([math.cos(a), 0.0, math.sin(a)])
        side = np.array([-math.sin(a), 0.0, math.cos(a)])
        p.add(WOOD, slab(hub, hub + 2.65 * u, 0.16, 0.12, normal=(0, 1, 0)))
        p.add(LIGHT_GREY, slab(hub + 0.55 * u + 0.3 * side, hub + 2.6 * u + 0.3 * side, 0.5, 0.05, normal=(0, 1, 0)))


@landmark("water_tower")
def _water_tower(p: Parts) -> None:
    legs = []
    for sx, sy in ((1, 1), (1, -1), (-1, -1), (-1, 1)):
        legs.append(rod((1.25 * sx, 1.25 * sy, 0.0), (0.95 * sx, 0.95 * sy, 4.6), 0.12, 8))
    for z in (1.6, 3.1):
        f = 1.25 - 0.3 * z / 4.6
        corners = [(f * sx, f * sy, z) for sx, sy in ((1, 1), (1, -1), (-1, -1), (-1, 1))]
        legs += [rod(corners[i], corners[(i + 1) % 4], 0.06, 6) for i in range(4)]
    p.add("#4d4d4d", *legs, rod((0, 0, 0), (0, 0, 4.6), 0.18, 10), cylinder(1.75, 4.5, 4.62, sections=20))
    p.add("#5fa8d3", cylinder(1.6, 4.6, 6.7, sections=20))
    p.add("#c0392b", frustum(1.7, 0.0, 6.7, 7.6, sections=20), sphere(0.12, (0, 0, 7.65)))


@landmark("igloo")
def _igloo(p: Parts) -> None:
    ice = "#eaf4fb"
    angles = np.radians(np.linspace(0.0, 90.0, 9))
    p.add(ice, lathe([(0.0, 0.0)] + [(1.8 * math.cos(a), 1.8 * math.sin(a)) for a in angles], sections=20))
    p.add("#a9c6dc", *[cylinder(math.sqrt(1.8**2 - z**2) + 0.015, z - 0.03, z + 0.03, sections=20)
                       for z in (0.45, 0.9, 1.3)])
    p.add(ice, extrude_y(half_disc(0.75, 8) * (1, 1.2), -2.45, -1.2))
    p.add("#263646", extrude_y(half_disc(0.5, 8) * (1, 1.2), -2.5, -2.4))


@landmark("tent")
def _tent(p: Parts) -> None:
    p.add(DARK_GREY, block(3.8, 3.1, 0.04))
    p.add(PURPLE, extrude_x([(-1.45, 0.0), (1.45, 0.0), (0.0, 2.2)], -1.8, 1.8))
    p.add("#2a1a40", extrude_x([(-0.6, 0.0), (0.6, 0.0), (0.0, 1.6)], 1.78, 1.86))
    p.add(LIGHT_GREY, rod((-1.95, 0, 2.2), (1.95, 0, 2.2), 0.05, 6),
          *[rod((1.9 * s, 0, 2.2), (2.3 * s, 0, 0.0), 0.025, 4) for s in (-1, 1)],
          *[cylinder(0.04, 0.0, 2.2, 1.85 * s, 0.0, 6) for s in (-1, 1)])


@landmark("phone_booth")
def _phone_booth(p: Parts) -> None:
    red = "#c8102e"
    p.add(red, block(1.2, 1.2, 0.15), block(1.1, 1.1, 2.55), block(1.2, 1.2, 0.12, z=2.55),
          rod((-0.6, 0, 2.67), (0.6, 0, 2.67), 0.42, 16), rod((0, -0.6, 2.67), (0, 0.6, 2.67), 0.42, 16))
    panes = []
    for side in ("front", "left", "right"):
        panes += windows(side, 0.55, 0.55, (-0.26, 0.0, 0.26), (0.9, 1.22, 1.54, 1.86), (0.2, 0.26))
    p.add("#d6eaf5", *panes)
    p.add(WHITE, *[panel(side, 0.55, 0.55, 0.0, 2.3, 0.75, 0.16) for side in ("front", "back", "left", "right")])
    p.add(GOLD, block(0.18, 0.18, 0.22, z=3.05))


@landmark("well_1")
def _well_1(p: Parts) -> None:
    p.add("#8d8f93", ring(0.95, 1.35, 0.0, 0.95))
    p.add(LIGHT_GREY, ring(0.9, 1.4, 0.95, 1.05))
    p.add(WATER, cylinder(1.0, 0.1, 0.7, sections=20))
    p.add(WOOD, *[block(0.2, 0.2, 2.75, x, 0.0, 0.0) for x in (-1.15, 1.15)], rod((-1.15, 0, 1.9), (1.3, 0, 1.9), 0.07))
    gable_roof(p, "#b03030", WOOD, 2.6, 1.4, 2.7, 0.75, 0.25, thick=0.1)
    p.add(DARK_GREY, rod((0, 0, 1.9), (0, 0, 1.35), 0.02, 4), frustum(0.18, 0.23, 1.05, 1.35))


@landmark("well_2")
def _well_2(p: Parts) -> None:
    brick = "#b5482e"
    p.add(brick, block(2.2, 0.35, 1.0, 0, -0.925), block(2.2, 0.35, 1.0, 0, 0.925), block(0.35, 1.5, 1.0, -0.925),
          block(0.35, 1.5, 1.0, 0.925))
    p.add(LIGHT_GREY, *[block(2.3, 0.45, 0.12, 0, y, 1.0) for y in (-0.925, 0.925)],
          *[block(0.45, 1.4, 0.12, x, 0, 1.0) for x in (-0.925, 0.925)])
    p.add(WATER, block(1.6, 1.6, 0.75))
    p.add(WOOD, *[block(0.2, 0.2, 2.3, x, 0.0, 1.0) for x in (-1.25, 1.25)], rod((-1.25, 0, 3.1), (1.4, 0, 3.1), 0.08),
          block(0.08, 0.08, 0.35, 1.4, 0.0, 2.75))
    p.add(DARK_GREY, rod((0, 0, 3.1), (0, 0, 2.1), 0.02, 4), frustum(0.2, 0.26, 1.7, 2.1))


@landmark("pyramid")
def _pyramid(p: Parts) -> None:
    p.add(SAND, place(creation.cone(radius=2.85, height=3.3, sections=4), rz=45.0))
    p.add(GOLD, place(creation.cone(radius=0.47, height=0.545, sections=4), (0, 0, 2.779), rz=45.0))
    half, height = 2.85 / math.sqrt(2), 3.3
    up_face = np.array([0.0, half, height]) / math.hypot(half, height)
    p.add("#3b2a18", slab((0.0, -half, 0.0), (0.0, -half, 0.0) + 1.1 * up_face, 0.7, 0.06,
                          normal=(0.0, -height, half)))


@landmark("arch")
def _arch(p: Parts) -> None:
    stone, light = "#b8563c", "#d07a5a"
    p.add(stone, *[block(0.8, 0.8, 3.0, x, 0.0, 0.0) for x in (-1.8, 1.8)])
    p.add(light, *[block(1.0, 1.0, 0.3, x, 0.0, z) for x in (-1.8, 1.8) for z in (0.0, 2.75)])
    angles = np.linspace(0.0, np.pi, 10)
    for k in range(9):
        a0, a1 = angles[k], angles[k + 1]
        quad = [(1.4 * math.cos(a0), 3.0 + 1.4 * math.sin(a0)), (2.2 * math.cos(a0), 3.0 + 2.2 * math.sin(a0)),
                (2.2 * math.cos(a1), 3.0 + 2.2 * math.sin(a1)), (1.4 * math.cos(a1), 3.0 + 1.4 * math.sin(a1))]
        p.add(stone if k % 2 == 0 else light, extrude_y(quad, -0.4, 0.4))
    p.add(light, block(0.6, 0.9, 0.95, 0.0, 0.0, 4.3))


@landmark("column")
def _column(p: Parts) -> None:
    marble = "#ede6d6"
    p.add(marble, block(1.6, 1.6, 0.35), frustum(0.78, 0.66, 0.35, 0.6, sections=24),
          prism(star_polygon(20, 0.6, 0.54), 0.55, 5.2), frustum(0.56, 0.8, 5.2, 5.5, sections=24),
          block(1.7, 1.7, 0.3, z=5.5))


@landmark("fountain")
def _fountain(p: Parts) -> None:
    stone = "#d6d0c4"
    p.add(stone, ring(2.0, 2.35, 0.0, 0.6, sections=24), cylinder(0.3, 0.4, 1.6), cylinder(0.15, 1.8, 2.35),
          lathe([(0.0, 1.5), (0.3, 1.5), (1.05, 1.85), (1.05, 1.95), (0.0, 1.75)], sections=20),
          lathe([(0.0, 2.3), (0.15, 2.3), (0.5, 2.5), (0.5, 2.56), (0.0, 2.45)], sections=16))
    p.add(WATER, cylinder(2.05, 0.0, 0.45, sections=24), cylinder(0.9, 1.75, 1.9, sections=20),
          cylinder(0.42, 2.4, 2.52, sections=12), frustum(0.12, 0.04, 2.45, 3.2, sections=8),
          sphere(0.1, (0, 0, 3.22), sub=0),
          *[rod((px, py, 1.92), (1.45 * px, 1.45 * py, 0.45), 0.05, 6) for px, py, _ in arc_points(8, 1.0, (0, 0), 0)])


@landmark("statue")
def _statue(p: Parts) -> None:
    stone, copper = "#a9a59b", "#45b08c"
    p.add(stone, block(1.6, 1.6, 0.3), block(1.3, 1.3, 1.6, z=0.3), block(1.5, 1.5, 0.2, z=1.8))
    p.add(copper, frustum(0.55, 0.28, 2.0, 3.9, sections=12), sphere(0.33, (0, 0, 3.95), scale=(1.1, 0.9, 0.8)),
          sphere(0.22, (0, 0, 4.4)), rod((0.3, 0, 4.0), (0.42, 0, 5.1), 0.09),
          rod((-0.3, 0, 3.95), (-0.42, -0.15, 3.5), 0.09),
          place(block(0.3, 0.12, 0.45), (-0.45, -0.18, 3.2), ry=-15.0),
          *[place(creation.cone(radius=0.05, height=0.3), (0, 0, 4.5), ry=a) for a in range(-60, 61, 20)])
    p.add(GOLD, rod((0.42, 0, 5.05), (0.44, 0, 5.35), 0.1), frustum(0.14, 0.0, 5.35, 5.7, 0.44, 0.0, sections=10))


@landmark("totem_pole")
def _totem_pole(p: Parts) -> None:
    segments = [("#8a5a33", 0.0, 1.3, 0.5), ("#c0392b", 1.3, 2.5, 0.48), ("#1f9e9e", 2.5, 3.7, 0.5),
                (YELLOW, 3.7, 4.9, 0.46)]
    for colour, z0, z1, r in segments:
        p.add(colour, cylinder(r, z0, z1, sections=12))
        mid = (z0 + z1) / 2
        p.add(WHITE, *[block(0.22, 0.12, 0.16, x, -r, mid + 0.12) for x in (-0.2, 0.2)])
        p.add(BLACK, *[block(0.1, 0.16, 0.1, x, -r - 0.02, mid + 0.15) for x in (-0.2, 0.2)],
              block(0.42, 0.12, 0.08, 0.0, -r, mid - 0.35))
    wing = [(0.3, 4.05), (1.4, 4.55), (1.35, 5.1), (0.3, 4.85)]
    p.add(BLACK, extrude_y(wing, -0.09, 0.09), extrude_y([(-x, z) for x, z in wing], -0.09, 0.09))
    p.add(ORANGE, place(creation.cone(radius=0.16, height=0.55, sections=8), (0, -0.42, 4.3), rx=90.0))


# ---- objects ----------------------------------------------------------------------------------------------


@landmark("barrel_1")
def _barrel_1(p: Parts) -> None:
    p.add("#a0622d", barrel_body(0.8, 1.9, 0.12))
    p.add("#2e2e2e", *hoops(0.8, 1.9, 0.12, (0.25, 0.6, 1.3, 1.65), 0.09))


@landmark("barrel_2")
def _barrel_2(p: Parts) -> None:
    p.add(BLUE, barrel_body(0.72, 2.0))
    p.add("#164aa3", *hoops(0.72, 2.0, 0.0, (0.67, 1.33), 0.08), cylinder(0.74, 1.94, 2.0, sections=20))
    p.add(LIGHT_GREY, cylinder(0.09, 2.0, 2.06, 0.4, 0.0, 8))


@landmark("barrel_3")
def _barrel_3(p: Parts) -> None:
    body = barrel_body(0.75, 2.0)
    bands = hoops(0.75, 2.0, 0.0, (1.0,), 0.35, proud=0.02)
    p.add(ORANGE, place(body, (0, 1.0, 0.9), rx=90.0))
    p.add(WHITE, *[place(b, (0, 1.0, 0.9), rx=90.0) for b in bands])
    p.add(WOOD, *[block(1.7, 0.3, 0.32, 0.0, y, 0.0) for y in (-0.6, 0.6)])


@landmark("red_barrel")
def _red_barrel(p: Parts) -> None:
    p.add(RED, barrel_body(0.78, 2.1))
    p.add(WHITE, *hoops(0.78, 2.1, 0.0, (0.65, 1.45), 0.16, proud=0.015))
    p.add(DARK_GREY, cylinder(0.8, 2.04, 2.1, sections=20), cylinder(0.8, 0.0, 0.06, sections=20))


@landmark("box_1")
def _box_1(p: Parts) -> None:
    s, t = 1.8, 0.16
    p.add(WOOD_LIGHT, block(s, s, s))
    frame = []
    for a in (-s / 2, s / 2):
        for b in (0.0, s):
            frame.append(block(s + t, t, t, 0.0, a, b - t / 2))
            frame.append(block(t, s + t, t, a, 0.0, b - t / 2))
        for b in (-s / 2, s / 2):
            frame.append(block(t, t, s, a, b, 0.0))
    for side, n in (((0, -1), (0, -1, 0)), ((0, 1), (0, 1, 0)), ((-1, 0), (-1, 0, 0)), ((1, 0), (1, 0, 0))):
        cx, cy = side[0] * s / 2, side[1] * s / 2
        lo = (cx - side[1] * s / 2, cy + side[0] * s / 2, 0.0)
        hi = (cx + side[1] * s / 2, cy - side[0] * s / 2, s)
        frame.append(slab(lo, hi, t, t, normal=n))
    p.add("#7a5126", *frame)


@landmark("box_2")
def _box_2(p: Parts) -> None:
    sx, sy, sz = 1.9, 1.5, 1.4
    cardboard = "#c9a46a"
    p.add(cardboard, block(sx, sy, sz))
    p.add("#5c4325", block(sx - 0.08, sy - 0.08, 0.02, z=sz))
    lean = math.radians(30.0)
    for sgn in (-1.0, 1.0):
        out, up = 0.7 * math.sin(lean), 0.7 * math.cos(lean)
        p.add(cardboard, slab((0, sgn * sy / 2, sz), (0, sgn * (sy / 2 + out), sz + up), sx, 0.04, normal=(0, sgn, 0)),
              slab((sgn * sx / 2, 0, sz), (sgn * (sx / 2 + out), 0, sz + up), sy, 0.04, normal=(sgn, 0, 0)))
    p.add("#9a7440", block(0.3, sy + 0.02, 0.55, 0, 0, sz - 0.55))


@landmark("container")
def _container(p: Parts) -> None:
    sx, sy, sz = 5.0, 2.2, 2.4
    p.add("#1b7f8a", block(sx, sy, sz))
    p.add("#125c64", *[block(0.12, sy + 0.1, sz - 0.2, x, 0.0, 0.1) for x in np.linspace(-2.2, 2.2, 13)],
          *[block(0.16, 0.16, sz, sgx * (sx / 2 - 0.06), sgy * (sy / 2 - 0.06), 0.0)
            for sgx in (-1, 1) for sgy in (-1, 1)])
    p.add(LIGHT_GREY, *[block(0.1, 0.06, 2.2, sx / 2 + 0.02, y, 0.1) for y in (-0.75, -0.35, 0.35, 0.75)])
    p.add(WHITE, panel("front", sx / 2, sy / 2, -0.8, 1.5, 2.0, 0.5, proud=0.07),
          panel("back", sx / 2, sy / 2, 0.8, 1.5, 2.0, 0.5, proud=0.07))


@landmark("cone_1")
def _cone_1(p: Parts) -> None:
    p.add(CYAN, frustum(1.15, 0.0, 0.0, 3.6, sections=24))


@landmark("cone_2")
def _cone_2(p: Parts) -> None:
    r, h = 1.45, 2.7
    p.add(MAGENTA, frustum(r, 0.0, 0.0, h, sections=8))
    p.add(WHITE, frustum(r * (1 - 1.0 / h) + 0.02, r * (1 - 1.35 / h) + 0.02, 1.0, 1.35, sections=8))


@landmark("traffic_cone")
def _traffic_cone(p: Parts) -> None:
    p.add(BLACK, block(1.2, 1.2, 0.12))
    radius = lambda z: 0.55 - 0.45 * (z - 0.12) / 1.63
    p.add(ORANGE, frustum(0.55, 0.1, 0.12, 1.75))
    p.add(WHITE, *[frustum(radius(a) + 0.012, radius(b) + 0.012, a, b) for a, b in ((0.7, 0.95), (1.15, 1.35))])


@landmark("tire_stack")
def _tire_stack(p: Parts) -> None:
    p.add("#1e1e1e", *[torus(0.55, 0.24, (0, 0, 0.24 + 0.46 * k), 20, 8) for k in range(5)])
    p.add("#6d6d6d", cylinder(0.36, 0.0, 2.1, sections=12))


@landmark("hay_bale")
def _hay_bale(p: Parts) -> None:
    hay, dark = "#e8c868", "#b98f34"
    p.add(hay, rod((0, -0.95, 1.05), (0, 0.95, 1.05), 1.05, 24))
    for y in (-0.95, 0.95):  # concentric rings on the flat ends
        discs = {r: rod((0, y, 1.05), (0, y + math.copysign(proud, y), 1.05), r, 20)
                 for r, proud in ((0.75, 0.02), (0.55, 0.04), (0.3, 0.06))}
        p.add(dark, discs[0.75], discs[0.3])
        p.add(hay, discs[0.55])
    p.add(dark, *[rod((0, y - 0.04, 1.05), (0, y + 0.04, 1.05), 1.075, 24) for y in (-0.55, 0.0, 0.55)])


@landmark("anvil")
def _anvil(p: Parts) -> None:
    p.add("#8b5a2b", cylinder(0.55, 0.0, 0.75, sections=16))
    iron = "#3c4048"
    p.add(iron, loft(rect(1.0, 0.6), 0.75, rect(0.55, 0.35), 1.0), block(0.5, 0.32, 0.27, z=0.99),
          block(1.3, 0.55, 0.3, 0.05, 0.0, 1.25),
          place(creation.cone(radius=0.27, height=0.75, sections=12), (0.7, 0.0, 1.42), ry=90.0),
          loft(rect(0.25, 0.55, -0.725), 1.35, rect(0.25, 0.35, -0.725), 1.55))


@landmark("globe")
def _globe(p: Parts) -> None:
    brass, centre = "#c9a227", np.array([0.0, 0.0, 1.97])
    p.add(brass, cylinder(0.65, 0.0, 0.15, sections=20), frustum(0.12, 0.08, 0.15, 0.9, sections=10))
    ring = place(torus(1.12, 0.045, sections=28, minor_sections=6), rx=90.0)
    axis = np.array([math.sin(math.radians(23.5)), 0.0, math.cos(math.radians(23.5))])
    p.add(brass, ring.apply_translation(centre), *[rod(centre + s * axis * 0.95, centre + s * axis * 1.12, 0.04)
                                                    for s in (-1, 1)])
    ball = creation.icosphere(subdivisions=2, radius=1.0)
    p.add("#1f6fd0", ball.copy().apply_translation(centre))
    c = ball.triangles_center
    land = np.sin(3.1 * c[:, 0] + 1.3) * np.cos(2.3 * c[:, 1]) + 0.6 * np.sin(4.7 * c[:, 2] + 2.0 * c[:, 0]) > 0.1
    ice = np.abs(c[:, 2]) > 0.88
    for colour, mask in (("#3da545", land & ~ice), (WHITE, ice)):
        tri = ball.vertices[ball.faces[mask]]
        verts = np.concatenate([tri * 0.98, tri * 1.035], axis=1).reshape(-1, 3) + centre
        base = np.array([[0, 2, 1], [3, 4, 5], [0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [2, 0, 3], [2, 3, 5]])
        faces = (base[None] + 6 * np.arange(int(mask.sum()))[:, None, None]).reshape(-1, 3)
        p.add(colour, _mesh(verts, faces))


@landmark("snowman")
def _snowman(p: Parts) -> None:
    p.add("#f7f9fc", *[sphere(r, (0, 0, z), sub=2) for r, z in ((0.8, 0.75), (0.58, 1.85), (0.42, 2.65))])
    p.add(BLACK, cylinder(0.48, 2.98, 3.04, sections=16), cylinder(0.3, 3.0, 3.5, sections=16),
          *[sphere(0.055, (x, -0.37, 2.76)) for x in (-0.14, 0.14)],
          *[sphere(0.07, (0, -0.57 + 0.03 * abs(z - 1.85) / 0.25, z)) for z in (1.62, 1.85, 2.08)])
    p.add(RED, cylinder(0.31, 3.04, 3.14, sections=16), torus(0.38, 0.1, (0, 0, 2.3), 20, 8),
          slab((0.25, -0.3, 2.3), (0.35, -0.45, 1.75), 0.16, 0.06, normal=(0, -1, 0)))
    p.add(ORANGE, place(creation.cone(radius=0.07, height=0.42, sections=8), (0, -0.4, 2.65), rx=90.0))
    arms = []
    for s in (-1, 1):
        arms += [rod((0.5 * s, 0, 1.95), (1.25 * s, 0, 2.45), 0.04, 6),
                 rod((1.1 * s, 0, 2.35), (1.3 * s, 0, 2.7), 0.03, 6)]
    p.add(WOOD_DARK, *arms)


@landmark("gorilla")
def _gorilla(p: Parts) -> None:
    fur, skin, silver = "#26262b", "#5e5a63", "#8d8d94"
    p.add(fur, place(sphere(1.0, sub=2, scale=(0.85, 0.7, 1.0)), (0, 0.1, 1.75), rx=-15.0),
          sphere(0.48, (0, -0.55, 2.75)), sphere(0.3, (0, -0.45, 3.1), scale=(0.8, 1.2, 1.0)),
          block(0.55, 0.15, 0.12, 0, -0.95, 2.82),
          *[sphere(0.38, (s * 0.75, -0.2, 2.35)) for s in (-1, 1)],
          *[rod((s * 0.75, -0.2, 2.35), (s * 1.05, -0.55, 1.2), 0.26, 10) for s in (-1, 1)],
          *[sphere(0.26, (s * 1.05, -0.55, 1.2)) for s in (-1, 1)],
          *[rod((s * 1.05, -0.55, 1.2), (s * 1.0, -0.8, 0.3), 0.24, 10) for s in (-1, 1)],
          *[sphere(0.3, (s * 1.0, -0.85, 0.3)) for s in (-1, 1)],
          *[rod((s * 0.45, 0.35, 1.0), (s * 0.55, 0.25, 0.3), 0.3, 10) for s in (-1, 1)])
    p.add(silver, sphere(1.0, (0, 0.5, 1.75), scale=(0.72, 0.42, 0.6)))
    p.add(skin, sphere(1.0, (0, -0.45, 1.9), scale=(0.55, 0.25, 0.5)),
          sphere(1.0, (0, -0.93, 2.62), scale=(0.3, 0.2, 0.24)),
          *[block(0.45, 0.7, 0.2, s * 0.55, 0.1, 0.0) for s in (-1, 1)])
    p.add(WHITE, *[sphere(0.06, (s * 0.17, -0.96, 2.76), sub=0) for s in (-1, 1)])


@landmark("stop_sign")
def _stop_sign(p: Parts) -> None:
    zc = 2.75
    p.add(GREY, cylinder(0.07, 0.0, zc, sections=10))
    p.add(WHITE, extrude_y(regular_polygon(8, 0.82, 22.5, (0.0, zc)), -0.035, 0.035))
    p.add("#d0021b", extrude_y(regular_polygon(8, 0.74, 22.5, (0.0, zc)), -0.05, 0.05))
    w, h, gap = 0.22, 0.36, 0.07
    x0 = -(4 * w + 3 * gap) / 2
    p.add(WHITE, *[m for k, ch in enumerate("STOP")
                   for m in seven_segment(ch, x0 + k * (w + gap), zc - h / 2, w, h, 0.055, -0.055)])


@landmark("street_lamp")
def _street_lamp(p: Parts) -> None:
    iron = "#1f2a24"
    p.add(iron, frustum(0.35, 0.2, 0.0, 0.6), cylinder(0.1, 0.6, 4.3, sections=10), sphere(0.14, (0, 0, 4.35)),
          rod((-0.9, 0, 4.0), (0.9, 0, 4.0), 0.06),
          *[frustum(0.34, 0.0, 4.55, 4.8, x, 0.0, sections=8) for x in (-0.9, 0.9)],
          *[cylinder(0.1, 3.95, 4.08, x, 0.0, 8) for x in (-0.9, 0.9)])
    p.add("#ffe45c", *[frustum(0.17, 0.28, 4.05, 4.57, x, 0.0, sections=8) for x in (-0.9, 0.9)])


@landmark("mailbox")
def _mailbox(p: Parts) -> None:
    p.add("#7b5233", block(0.2, 0.2, 1.45), block(0.45, 0.8, 0.06, z=1.44))
    blue = "#2a4d9b"
    p.add(blue, block(0.6, 1.2, 0.45, z=1.5), rod((0, -0.6, 1.95), (0, 0.6, 1.95), 0.3, 16))
    p.add(DARK_GREY, block(0.5, 0.04, 0.55, 0.0, -0.61, 1.55))
    p.add(RED, block(0.05, 0.05, 0.6, 0.33, 0.25, 1.6), block(0.05, 0.32, 0.2, 0.33, 0.1, 2.0))


@landmark("bench")
def _bench(p: Parts) -> None:
    wood, iron = "#c2652a", "#232323"
    p.add(wood, *[block(3.6, 0.26, 0.08, 0.0, y, 0.72) for y in (-0.32, 0.0, 0.32)])
    back = (0.0, -math.cos(math.radians(15.0)), math.sin(math.radians(15.0)))
    p.add(wood, *[slab((-1.8, y, z), (1.8, y, z), 0.22, 0.07, normal=back) for y, z in ((0.5, 1.05), (0.58, 1.35))])
    frame = []
    for x in (-1.5, 1.5):
        frame += [block(0.1, 0.1, 0.72, x, -0.38, 0.0), rod((x, 0.38, 0.0), (x, 0.62, 1.5), 0.05, 6),
                  block(0.1, 0.9, 0.08, x, 0.0, 0.64), block(0.1, 0.75, 0.06, x, -0.02, 1.0),
                  block(0.08, 0.08, 0.3, x, -0.38, 0.72)]
    p.add(iron, *frame)


@landmark("satellite_dish")
def _satellite_dish(p: Parts) -> None:
    grey = "#7d838b"
    p.add(grey, block(1.2, 1.2, 0.35), cylinder(0.16, 0.35, 2.05, sections=12), block(0.4, 0.4, 0.3, z=1.9))
    rs = np.linspace(0.0, 1.55, 7)
    profile = [(r, 0.45 * (r / 1.5) ** 2) for r in rs] + [(r, 0.12 + 0.4 * (r / 1.55) ** 2) for r in rs[::-1]]
    tilt, at = 40.0, np.array([0.0, 0.0, 2.2])
    p.add(WHITE, place(lathe(profile, sections=20), at, rx=tilt))
    normal = np.array([0.0, -math.sin(math.radians(tilt)), math.cos(math.radians(tilt))])
    focus = at + normal * 1.05
    rotation = tf.rotation_matrix(math.radians(tilt), (1, 0, 0))[:3, :3]
    rim = [at + rotation @ np.array(pt) for pt in arc_points(3, 1.5, (0, 0), 0.45, 90.0)]
    p.add(DARK_GREY, *[rod(r, focus, 0.03, 6) for r in rim], cylinder(0.12, -0.12, 0.12).apply_translation(focus))


# ---- vehicles ---------------------------------------------------------------------------------------------


@landmark("car")
def _car(p: Parts) -> None:
    body = "#f6c70f"
    p.add(body, block(4.0, 1.8, 0.65, z=0.35), block(1.34, 1.44, 0.06, -0.3, 0.0, 1.6))
    p.add("#9ad0f5", loft(rect(2.1, 1.64, -0.2), 1.0, rect(1.3, 1.4, -0.3), 1.6))
    p.add(BLACK, *[rod((x, 0.78 * s, 0.38), (x, 1.0 * s, 0.38), 0.38, 16) for x in (-1.3, 1.3) for s in (-1, 1)],
          block(0.1, 1.8, 0.2, 2.02, 0.0, 0.35), block(0.1, 1.8, 0.2, -2.02, 0.0, 0.35))
    p.add(LIGHT_GREY, *[rod((x, 1.0 * s, 0.38), (x, 1.03 * s, 0.38), 0.18, 10) for x in (-1.3, 1.3) for s in (-1, 1)])
    p.add(WHITE, *[block(0.06, 0.35, 0.15, 2.01, y, 0.75) for y in (-0.6, 0.6)])
    p.add(RED, *[block(0.06, 0.35, 0.15, -2.01, y, 0.75) for y in (-0.6, 0.6)])


@landmark("tank")
def _tank(p: Parts) -> None:
    olive, dark = "#5b6e2d", "#4b5a24"
    p.add(olive, block(4.0, 1.9, 0.5, z=0.35), loft(rect(4.2, 2.5), 0.85, rect(3.6, 2.2), 1.25))
    p.add("#2f2f2f", *[block(4.4, 0.5, 0.8, 0.0, s * 1.0, 0.05) for s in (-1, 1)])
    p.add("#585858", *[rod((x, s * 1.25, 0.42), (x, s * 1.3, 0.42), 0.32, 12) for x in np.linspace(-1.6, 1.6, 5)
                       for s in (-1, 1)])
    p.add(dark, lathe([(0.0, 1.25), (1.0, 1.25), (0.85, 1.75), (0.0, 1.8)], -0.2, 0.0, sections=16),
          rod((0.6, 0, 1.5), (2.65, 0, 1.55), 0.09), rod((2.5, 0, 1.55), (2.8, 0, 1.555), 0.13, 10),
          cylinder(0.25, 1.75, 1.9, -0.4, 0.3, 10))
    p.add(WHITE, extrude_y(star_polygon(5, 0.2, 0.08, centre=(-0.2, 1.5)), -0.97, -0.9))


@landmark("boat")
def _boat(p: Parts) -> None:
    keel = [(-1.9, -0.25), (1.1, -0.25), (2.0, 0.0), (1.1, 0.25), (-1.9, 0.25)]
    water = [(-2.2, -0.8), (1.0, -0.8), (2.4, 0.0), (1.0, 0.8), (-2.2, 0.8)]
    stripe = [(-2.25, -0.85), (1.0, -0.85), (2.5, 0.0), (1.0, 0.85), (-2.25, 0.85)]
    deck = [(-2.3, -0.9), (1.0, -0.9), (2.6, 0.0), (1.0, 0.9), (-2.3, 0.9)]
    p.add("#c0392b", loft(keel, 0.45, water, 0.95))
    p.add(NAVY, loft(water, 0.95, stripe, 1.15))
    p.add(WHITE, loft(stripe, 1.15, deck, 1.55), block(1.2, 1.0, 0.5, -0.7, 0.0, 1.55))
    p.add("#b07a42", prism(np.asarray(deck) * 0.96, 1.55, 1.6))
    p.add(WOOD_DARK, *[block(0.3, 1.2, 0.5, x, 0.0, 0.0) for x in (-1.0, 1.0)])
    p.add(LIGHT_GREY, cylinder(0.07, 1.6, 6.3, 0.2, 0.0, 8), rod((0.2, 0, 2.1), (-1.9, 0, 2.1), 0.04, 6))
    p.add("#fafafa", extrude_y([(0.12, 2.15), (-1.85, 2.15), (0.12, 6.1)], -0.02, 0.02),
          extrude_y([(0.3, 1.75), (2.35, 1.65), (0.3, 5.6)], -0.02, 0.02))
    p.add(NAVY, *windows("front", 1.3, 0.5, (-1.0, -0.4), (1.7,), (0.35, 0.22)),
          *windows("back", 1.3, 0.5, (-1.0, -0.4), (1.7,), (0.35, 0.22)))


# ==================================================================================================
# Public catalogue.
# ==================================================================================================

_UNPAIRED = sorted(set(_BUILDERS) ^ {c.name for c in CLASSES})
if _UNPAIRED:
    raise RuntimeError(f"landmarks without a builder or builders without a catalogue entry: {_UNPAIRED}")
CATALOGUE: tuple[LandmarkModel, ...] = tuple(
    LandmarkModel(c.name, c.noun_phrase, c.radius, functools.partial(_run, _BUILDERS[c.name])) for c in CLASSES)
_BY_NAME: dict[str, LandmarkModel] = {m.name: m for m in CATALOGUE}


def model_by_name(name: str) -> LandmarkModel:
    """Catalogue entry by its unique name (KeyError if unknown)."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise KeyError(f"unknown landmark {name!r}; known: {sorted(_BY_NAME)}") from None


# ==================================================================================================
# Measurements shared by the asset writer and the tests.
# ==================================================================================================


def merged_arrays(parts: Iterable[LandmarkPart]) -> tuple[np.ndarray, np.ndarray]:
    """All parts as one (vertices, faces) pair."""
    vertices, faces, offset = [], [], 0
    for part in parts:
        vertices.append(np.asarray(part.mesh.vertices, float))
        faces.append(np.asarray(part.mesh.faces, np.int64) + offset)
        offset += len(part.mesh.vertices)
    return np.vstack(vertices), np.vstack(faces)


def axis_hits(vertices: np.ndarray, faces: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """Heights (descending, duplicates within 1e-6 merged) at which the vertical line x = y = 0 crosses
    the triangles, i.e. the hits of a downward ray cast from above."""
    tri = np.asarray(vertices, float)[np.asarray(faces)]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    e1, e2, q = b[:, :2] - a[:, :2], c[:, :2] - a[:, :2], -a[:, :2]
    den = e1[:, 0] * e2[:, 1] - e2[:, 0] * e1[:, 1]
    ok = np.abs(den) > 1e-12
    den = np.where(ok, den, 1.0)
    u = (q[:, 0] * e2[:, 1] - e2[:, 0] * q[:, 1]) / den
    v = (e1[:, 0] * q[:, 1] - q[:, 0] * e1[:, 1]) / den
    inside = ok & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps)
    z = np.sort((a[:, 2] + u * (b[:, 2] - a[:, 2]) + v * (c[:, 2] - a[:, 2]))[inside])[::-1]
    if len(z) == 0:
        return z
    keep = np.concatenate([[True], np.diff(z) < -1e-6])
    return z[keep]


def axis_z(parts: Iterable[LandmarkPart]) -> float:
    """A height on the vertical axis well inside the model: the middle of the longest stretch of the axis
    that lies inside some part. Each part is a closed mesh, so its own hits pair up as entry and exit;
    the stretches of all parts are merged, since parts may overlap (a barrel's hoops cross its body)."""
    intervals = []
    for part in parts:
        hits = axis_hits(np.asarray(part.mesh.vertices), np.asarray(part.mesh.faces))
        intervals += [(hits[i + 1], hits[i]) for i in range(0, len(hits) - 1, 2)]
    if not intervals:
        raise ValueError("the vertical axis misses the mesh")
    merged: list[list[float]] = []
    for lo, hi in sorted(intervals):
        if merged and lo <= merged[-1][1] + 1e-6:
            merged[-1][1] = max(merged[-1][1], hi)
        else:
            merged.append([lo, hi])
    lo, hi = max(merged, key=lambda iv: iv[1] - iv[0])
    return float((lo + hi) / 2)


def footprint_radius(vertices: np.ndarray) -> float:
    """Largest horizontal distance of a vertex from the vertical axis."""
    return float(np.max(np.hypot(vertices[:, 0], vertices[:, 1])))
