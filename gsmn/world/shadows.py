"""The paper's look in one render pass: the static world's shadows baked into the scene once per world.

MuJoCo draws a shadow-casting light in extra passes every frame (render_gl3.c, `mjr_render`): the scene lit by the
lights that cast no shadow (here the headlight), a depth map from the sun, then the scene again lit by the sun alone
with the depth map's test, added to the first. On these CPUs (Mesa's llvmpipe) those passes are two thirds of a
frame. Nothing in this world moves but the drone, so its shadows are the same in every frame and are drawn once per
world (`camera.shadow_method = "baked"`), and the sun then lights the scene in the headlight's single pass:

- on the ground, `bake` projects every landmark triangle along the sun onto the field and darkens the field's texture
  there to what the headlight alone gives it;
- on the landmarks, `face_shades` casts rays toward the sun from every face's corners and centre (MuJoCo's own ray
  casting on the world compiled once without it); a face in another's shadow goes into a darker geom of its own part,
  its colour scaled to what the headlight alone would give it, and a face the shadow's edge crosses is split first.

One pass differs from the two in one more way: the fixed-function pipeline clamps a vertex's lit colour to 1 before
the texture multiplies it. On the white-textured field the headlight and the sun together reach 1.15, so one pass
would cap it where two passes add up to 1.15 times the texture. `LIGHT_SCALE` keeps every sum below 1: all lights
and the sky are scaled down by it before rendering and the image is scaled back up after (`restore`), at the cost
of the lowest bit. Left out: shadows on the lakes and beyond the field, the drone's own shadow, the outline of
MuJoCo's shadows (a shadow-map texel larger and stepped). Measured against MuJoCo's shadows: docs/experiments.md,
"Rendering at the paper's look".
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
from PIL import Image, ImageDraw

LIGHT_SCALE = 2  # lights and sky divided by it, images multiplied by it: no lit colour reaches the clamp
FIELD_TEXTURE = "field_baked"  # the field's texture in this mode: the grass checker over the whole field, shadowed
GRASS_TEXTURE = "grass"  # the checker the paper's look repeats over the field
GRASS_REPEAT = 10  # its repeats over the field (the field material's texrepeat in the paper's look)
SUPERSAMPLE = 3  # triangles drawn at 3x the texture's resolution, then averaged: partly shadowed texels


def scale_lights(model: mujoco.MjModel) -> None:
    """Divide every light and the sky by LIGHT_SCALE (before a renderer uploads the model)."""
    for part in ("ambient", "diffuse", "specular"):
        getattr(model.vis.headlight, part)[:] /= LIGHT_SCALE
        getattr(model, f"light_{part}")[:] /= LIGHT_SCALE
    for t in range(model.ntex):
        if model.tex_type[t] == mujoco.mjtTexture.mjTEXTURE_SKYBOX:
            adr, n = model.tex_adr[t], model.tex_height[t] * model.tex_width[t] * model.tex_nchannel[t]
            sky = model.tex_data[adr:adr + n].astype(np.float32) / LIGHT_SCALE
            model.tex_data[adr:adr + n] = np.round(sky).astype(np.uint8)


def restore(image: np.ndarray) -> np.ndarray:
    """An image rendered with scaled lights at the paper's brightness (uint8)."""
    return np.minimum(image.astype(np.uint16) * LIGHT_SCALE, 255).astype(np.uint8)


def _texture(model: mujoco.MjModel, name: str) -> tuple[np.ndarray, int, int]:
    t = model.texture(name).id
    h, w, c = int(model.tex_height[t]), int(model.tex_width[t]), int(model.tex_nchannel[t])
    adr = int(model.tex_adr[t])
    return model.tex_data[adr:adr + h * w * c].reshape(h, w, c), h, w


def landmark_triangles(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """Every landmark mesh triangle in world coordinates (n, 3, 3), from the current kinematics."""
    out = []
    for g in range(model.ngeom):
        mesh = int(model.geom_dataid[g])
        if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH or mesh < 0:
            continue
        if not model.body(model.geom_bodyid[g]).name.startswith("landmark_"):
            continue
        va, vn = int(model.mesh_vertadr[mesh]), int(model.mesh_vertnum[mesh])
        fa, fn = int(model.mesh_faceadr[mesh]), int(model.mesh_facenum[mesh])
        verts = model.mesh_vert[va:va + vn] @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]
        out.append(verts[model.mesh_face[fa:fa + fn]])
    return np.concatenate(out) if out else np.zeros((0, 3, 3))


def shadow_cover(triangles: np.ndarray, sun_dir: np.ndarray, field_size: float, size: int) -> np.ndarray:
    """The share of each texel of a (size, size) grid over the field (row 0 north, column 0 west) that the
    triangles' shadows cover, the sun shining along `sun_dir` (pointing down)."""
    d = np.asarray(sun_dir, dtype=float)
    t = -triangles[..., 2:3] / d[2]  # along the sun to the ground, z = 0
    ground = triangles[..., :2] + t * d[:2]
    px = size * SUPERSAMPLE / field_size
    cols, rows = ground[..., 0] * px, (field_size - ground[..., 1]) * px
    canvas = Image.new("L", (size * SUPERSAMPLE, size * SUPERSAMPLE), 0)
    draw = ImageDraw.Draw(canvas)
    for c, r in zip(cols.tolist(), rows.tolist(), strict=True):
        draw.polygon([(c[0], r[0]), (c[1], r[1]), (c[2], r[2])], fill=255)
    small = canvas.resize((size, size), Image.Resampling.BOX)
    return np.asarray(small, dtype=np.float32) / 255.0


def headlight_share(model: mujoco.MjModel, pitch_deg: float) -> float:
    """The share of the ground's light that the headlight gives, seen by a camera pitched down `pitch_deg`: what
    is left of the ground's colour in the sun's shadow (MuJoCo's shadow pass adds the sun only where it is lit)."""
    h = model.vis.headlight
    head = float(h.ambient[0] + h.diffuse[0] * max(0.0, math.sin(math.radians(pitch_deg))))
    sun = 0.0
    for i in range(model.nlight):
        if model.light_castshadow[i]:
            sun += float(model.light_ambient[i, 0] + model.light_diffuse[i, 0] * max(0.0, -model.light_dir[i, 2]))
    return head / (head + sun) if head + sun > 0 else 1.0


def bake(model: mujoco.MjModel, data: mujoco.MjData, field_size: float, pitch_deg: float) -> None:
    """Write the field's texture: the grass checker tiled over the field, darkened where the landmarks shadow it
    from every light marked to cast shadows (before a renderer uploads the model; the lights not yet scaled)."""
    grass, gh, gw = _texture(model, GRASS_TEXTURE)
    field, fh, fw = _texture(model, FIELD_TEXTURE)
    # the repeated texture's phase on the field: MuJoCo maps x in [-s, s] of a plane to s-coordinates
    # 0.5 * repeat * x / s - 0.5, so the field's west edge is half a tile into the checker
    tiled = np.tile(grass, (GRASS_REPEAT + 1, GRASS_REPEAT + 1, 1))
    tiled = tiled[gh // 2:gh // 2 + fh, gw // 2:gw // 2 + fw]
    cover = np.zeros((fh, fw), dtype=np.float32)
    triangles = landmark_triangles(model, data)
    for i in range(model.nlight):
        if model.light_castshadow[i] and len(triangles):
            cover = np.maximum(cover, shadow_cover(triangles, model.light_dir[i], field_size, fh))
    keep = 1.0 - cover * (1.0 - headlight_share(model, pitch_deg))
    field[...] = np.round(tiled * keep[..., None]).astype(np.uint8)


# -- the landmarks' own shadows -----------------------------------------------------------------------------------
SHADE_BINS = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8)  # a shadowed face's colour factor, rounded to one of these: a geom each
HEADLIGHT_FACING = 0.5  # the headlight's diffuse term on a landmark face, taken as its mean over views
SPLIT_DEPTH = 5  # a face the shadow's edge crosses is halved up to this many times
MIN_EDGE = 0.1  # ... while its longest edge is over 10 cm (a texel of MuJoCo's shadow map: 64.7 m / 1024 = 6 cm)


def _world_parts(world, catalogue) -> list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]]:
    """(landmark, part, vertices in the part's frame (V, 3), in the world (V, 3), faces (F, 3)) of every landmark
    part, placed as build_spec places them (scaled, turned by the yaw, at x, y)."""
    by_name = {m.name: m for m in catalogue}
    out = []
    for i, lm in enumerate(world.landmarks):
        c, s = math.cos(lm.yaw), math.sin(lm.yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        for k, part in enumerate(by_name[lm.model].parts):
            local = np.asarray(part.vertices, dtype=float)
            out.append((i, k, local, (local * lm.scale) @ R.T + [lm.x, lm.y, 0.0], np.asarray(part.faces)))
    return out


def ray_test(model: mujoco.MjModel, data: mujoco.MjData, exclude_body: int):
    """Whether a ray from each point toward `toward` meets a geom of the compiled world (MuJoCo's own ray casting,
    against every geom but those of `exclude_body`)."""
    geomid = np.zeros(1, dtype=np.int32)

    def blocked(points: np.ndarray, toward: np.ndarray) -> np.ndarray:
        return np.array([mujoco.mj_ray(model, data, p, toward, None, 1, exclude_body, geomid) >= 0
                         for p in points], dtype=bool)

    return blocked


def face_shades(world, catalogue, sun_dir: np.ndarray, headlight: tuple[float, float], sun: float, blocked
                ) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every landmark part as vertices (in its frame), faces and a colour factor per face: 1 where the sun reaches
    the face (or the face turns away from it, unlit by the sun either way), else what is left of its lit colour
    under the headlight alone (ambient + diffuse * HEADLIGHT_FACING over that plus the sun's diffuse on it, rounded
    to SHADE_BINS). A face is judged by rays toward the sun from its corners and its centre; one the shadow's edge
    crosses (they disagree) is split at its longest edge, up to SPLIT_DEPTH times, so that the edge falls between
    faces. `headlight` (ambient, diffuse) and `sun` (diffuse) as the model's lights are before scaling;
    `blocked(points, toward)` says which rays toward the sun meet the world (`ray_test`, on the world compiled
    without the split)."""
    toward = -np.asarray(sun_dir, dtype=float) / np.linalg.norm(sun_dir)
    head = headlight[0] + headlight[1] * HEADLIGHT_FACING
    bins = np.asarray(SHADE_BINS)
    out = {}
    for i, k, local, placed, faces in _world_parts(world, catalogue):
        local_v, world_v = local.copy(), placed.copy()
        known = np.full(len(world_v), -1, dtype=np.int8)  # a vertex's ray: -1 not cast, 0 free, 1 blocked
        done_faces, shades = [np.zeros((0, 3), dtype=np.int64)], [np.zeros(0)]
        todo, depth = np.asarray(faces, dtype=np.int64), 0
        while len(todo):
            tri = world_v[todo]
            normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            length = np.linalg.norm(normal, axis=1)
            lit = np.where(length > 0, (normal @ toward) / np.maximum(length, 1e-12), 0.0)
            facing = lit > 0.05
            corners = np.unique(todo[facing])
            ask = corners[known[corners] < 0]
            known[ask] = blocked(world_v[ask] + 2e-3 * toward, toward)
            centre = np.zeros(len(todo), dtype=bool)
            centre[facing] = blocked(tri[facing].mean(axis=1) + 2e-3 * toward, toward)
            hits = np.concatenate([centre[:, None], known[todo] == 1], axis=1) & facing[:, None]
            longest = np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=2).max(axis=1)
            split = facing & hits.any(axis=1) & ~hits.all(axis=1) & (depth < SPLIT_DEPTH) & (longest > MIN_EDGE)
            keep = ~split
            factor = np.where(centre, bins[np.abs((head / (head + sun * np.maximum(lit, 1e-6)))[:, None]
                                                  - bins[None]).argmin(axis=1)], 1.0)
            done_faces.append(todo[keep])
            shades.append(factor[keep])
            todo, local_v, world_v, known = _split_longest(todo[split], local_v, world_v, known)
            depth += 1
        out[(i, k)] = (local_v, np.concatenate(done_faces).astype(np.int32), np.concatenate(shades))
    return out


def _split_longest(faces: np.ndarray, local_v: np.ndarray, world_v: np.ndarray, known: np.ndarray):
    """Each face halved at the middle of its longest edge: the two halves, and the vertex lists (and their rays'
    results, unknown for the new ones) with the middles appended."""
    if not len(faces):
        return faces, local_v, world_v, known
    tri = world_v[faces]
    edges = np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=2)  # edge e runs from corner e to corner e + 1
    e = edges.argmax(axis=1)
    rows = np.arange(len(faces))
    a, b, c = faces[rows, e], faces[rows, (e + 1) % 3], faces[rows, (e + 2) % 3]
    m = np.arange(len(world_v), len(world_v) + len(faces))
    local_v = np.concatenate([local_v, (local_v[a] + local_v[b]) / 2])
    world_v = np.concatenate([world_v, (world_v[a] + world_v[b]) / 2])
    known = np.concatenate([known, np.full(len(faces), -1, dtype=np.int8)])
    halves = np.concatenate([np.stack([a, m, c], axis=1), np.stack([m, b, c], axis=1)])
    return halves, local_v, world_v, known
