"""Pinhole camera geometry shared by tests, labels and the dashboard (numpy).

Conventions (see gsmn.world.sim): camera frame x right, y down, z forward; the centre of the top-left
pixel is at (0.5, 0.5); T_world_camera maps camera coordinates to world coordinates.
"""

from __future__ import annotations

import numpy as np


def project_points(K: np.ndarray, T_world_camera: np.ndarray, points_w: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Project world points (N, 3) to pixels. Returns uv (N, 2) and depth along the optical axis (N,)."""
    T_camera_world = np.linalg.inv(T_world_camera)
    p_c = points_w @ T_camera_world[:3, :3].T + T_camera_world[:3, 3]  # (N, 3)
    depth = p_c[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (p_c @ K.T)[:, :2] / depth[:, None]
    return uv, depth


def in_image(uv: np.ndarray, depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Which projected points (N,) lie in front of the camera and inside the image."""
    return (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
