"""The paper's look in one render pass: the static world's shadows baked into the field's texture once per world.

MuJoCo draws a shadow-casting light in extra passes every frame (render_gl3.c, `mjr_render`): the scene lit by the
lights that cast no shadow (here the headlight), a depth map from the sun, then the scene again lit by the sun alone
with the depth map's test, added to the first. On these CPUs (Mesa's llvmpipe) those passes are two thirds of a
frame. Nothing in this world moves but the drone, so the landmarks' shadows on the ground are the same in every
frame: `bake` computes them once per world by projecting every landmark triangle along the sun onto the ground,
and darkens the field's texture there to what the headlight alone gives it. The sun then lights the scene in the
same single pass as the headlight (`camera.shadow_method = "baked"`).

One pass differs from the two in one more way: the fixed-function pipeline clamps a vertex's lit colour to 1 before
the texture multiplies it. On the white-textured field the headlight and the sun together reach 1.15, so one pass
would cap it where two passes add up to 1.15 times the texture. `LIGHT_SCALE` keeps every sum below 1: all lights
and the sky are scaled down by it before rendering and the image is scaled back up after (`restore`), at the cost
of the lowest bit. What the baked shadows leave out: a landmark's shadow on another landmark or on itself (a face
turned away from the sun is dark either way), shadows on the lakes and beyond the field, and the drone's own shadow.
Measured against MuJoCo's shadows: docs/experiments.md, "Rendering at the paper's look".
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
