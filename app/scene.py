"""Draw a WorldSpec into a viser scene with the same meshes the simulator uses (assets/landmarks)."""

from __future__ import annotations

import math

import numpy as np
import viser

from gsmn.world.assets import AssetModel
from gsmn.world.spec import WorldSpec


def yaw_wxyz(yaw: float) -> tuple[float, float, float, float]:
    return (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))


def R_to_wxyz(R: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) of a rotation matrix."""
    import mujoco

    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.asarray(R, dtype=float).ravel())
    return q


def _rgb(rgba: tuple[float, ...]) -> tuple[int, int, int]:
    return tuple(int(round(255 * c)) for c in rgba[:3])


def draw_world(scene: viser.SceneApi, world: WorldSpec, catalogue: tuple[AssetModel, ...]) -> None:
    """(Re)draw field, lakes and landmarks under /world; replaces what was there."""
    by_name = {m.name: m for m in catalogue}
    L = world.field_size
    scene.add_frame("/world", show_axes=False)  # children are placed relative to their parent
    scene.add_box("/world/field", color=(92, 150, 62), dimensions=(L, L, 0.02), position=(L / 2, L / 2, -0.011),
                  flat_shading=True, cast_shadow=False)
    scene.add_grid("/world/grid", width=L, height=L, cell_size=1.5, section_size=7.5, position=(L / 2, L / 2, 0.002),
                   cell_color=(84, 140, 58), section_color=(70, 118, 48), shadow_opacity=0.0)
    for i, lake in enumerate(world.lakes):
        n = 48
        t = np.linspace(0, 2 * math.pi, n, endpoint=False)
        ring = np.stack([lake.radius_x * np.cos(t), lake.radius_y * np.sin(t), np.full(n, 0.005)], 1)
        verts = np.vstack([[0, 0, 0.005], ring]).astype(np.float32)
        faces = np.array([[0, 1 + k, 1 + (k + 1) % n] for k in range(n)], dtype=np.int32)
        scene.add_mesh_simple(f"/world/lake_{i}", verts, faces, color=(51, 107, 191), wxyz=yaw_wxyz(lake.yaw),
                              position=(lake.x, lake.y, 0.0), cast_shadow=False)
    for i, lm in enumerate(world.landmarks):
        model = by_name[lm.model]
        frame = f"/world/landmark_{i}"
        scene.add_frame(frame, show_axes=False, wxyz=yaw_wxyz(lm.yaw), position=(lm.x, lm.y, 0.0))
        for k, part in enumerate(model.parts):
            scene.add_mesh_simple(f"{frame}/part_{k}", part.vertices, part.faces, color=_rgb(part.rgba),
                                  scale=lm.scale, flat_shading=True)
        scene.add_label(f"/world/label_{i}", lm.noun_phrase, position=(lm.x, lm.y, model.height * lm.scale + 0.6),
                        anchor="bottom-center")
