"""Render every landmark model with MuJoCo and tile them into a labelled contact sheet.

    MUJOCO_GL=egl python scripts/landmark_sheet.py [--assets assets] [--out docs/landmarks.png]

Meshes are read through `gsmn.world.assets.load_catalogue`, i.e. exactly what the simulator shows.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from PIL import Image, ImageDraw, ImageFont  # noqa: E402

from gsmn.world.assets import ASSETS_DIR, load_catalogue  # noqa: E402

COLS, ROWS = 9, 7
TILE_W, TILE_H, LABEL_H = 200, 150, 30

_SCENE = """
<mujoco>
  <visual>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.35 0.35 0.35" specular="0 0 0"/>
    <quality shadowsize="2048"/>
    <map znear="0.05" zfar="400"/>
  </visual>
  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.65 0.8 0.95" rgb2="0.9 0.95 1" width="64" height="64"/>
  </asset>
  <worldbody>
    <light directional="true" dir="0.35 0.5 -1" diffuse="0.6 0.6 0.6" specular="0.1 0.1 0.1" castshadow="true"/>
    <geom name="ground" type="plane" size="60 60 0.1" rgba="0.47 0.6 0.4 1" contype="0" conaffinity="0"/>
  </worldbody>
</mujoco>
"""


def render_tiles(assets_dir: Path) -> list[tuple[str, str, np.ndarray]]:
    """One (name, phrase, image) per model, each rendered alone at the origin."""
    catalogue = load_catalogue(assets_dir)
    spec = mujoco.MjSpec.from_string(_SCENE)
    for i, model in enumerate(catalogue):
        body = spec.worldbody.add_body(name=f"model_{i}")
        for k, part in enumerate(model.parts):
            mesh = spec.add_mesh(name=f"m{i}_{k}")
            mesh.uservert = part.vertices.ravel().tolist()
            mesh.userface = part.faces.ravel().tolist()
            mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
            body.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh.name, rgba=list(part.rgba),
                          contype=0, conaffinity=0)
    m = spec.compile()
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    rgba = m.geom_rgba.copy()
    renderer = mujoco.Renderer(m, TILE_H, TILE_W)
    camera = mujoco.MjvCamera()
    tiles = []
    for i, model in enumerate(catalogue):
        body_id = m.body(f"model_{i}").id
        visible = (m.geom_bodyid == body_id) | (m.geom_bodyid == 0)
        m.geom_rgba[:] = rgba
        m.geom_rgba[~visible, 3] = 0.0
        size = max(model.height, 2.0 * model.footprint_radius)
        camera.lookat[:] = (0.0, 0.0, 0.45 * model.height)
        camera.distance = 1.25 * size + 2.5
        camera.azimuth, camera.elevation = 62.0, -22.0
        renderer.update_scene(d, camera)
        tiles.append((model.name, model.noun_phrase, renderer.render().copy()))
    renderer.close()
    return tiles


def contact_sheet(tiles: list[tuple[str, str, np.ndarray]]) -> Image.Image:
    sheet = Image.new("RGB", (COLS * TILE_W, ROWS * (TILE_H + LABEL_H)), "white")
    draw = ImageDraw.Draw(sheet)
    try:
        font = ImageFont.load_default(size=12)
    except TypeError:  # Pillow < 10.1
        font = ImageFont.load_default()
    for i, (name, phrase, image) in enumerate(tiles):
        x, y = (i % COLS) * TILE_W, (i // COLS) * (TILE_H + LABEL_H)
        sheet.paste(Image.fromarray(image), (x, y))
        draw.text((x + 4, y + TILE_H + 1), f"{i}: {name}", fill=(0, 0, 0), font=font)
        draw.text((x + 4, y + TILE_H + 15), f'"{phrase}"', fill=(40, 40, 150), font=font)
        draw.rectangle((x, y, x + TILE_W - 1, y + TILE_H + LABEL_H - 1), outline=(200, 200, 200))
    return sheet


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--assets", type=Path, default=ASSETS_DIR)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "landmarks.png")
    args = parser.parse_args()
    sheet = contact_sheet(render_tiles(args.assets))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(args.out, optimize=True)
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
