"""Labels of the auxiliary objectives, from the WorldSpec, the instruction and the TRUE poses (paper: Auxiliary
Objectives). Pose noise, when on, only affects what the model sees, never the labels.

- visible (B, T, M): the landmark's centre (x, y, 0) projects inside the image, in front of the camera, at a real
  step. These are O_FPV of the paper.
- landmark_cell_w (B, M, 2): the world-map cell (row, col) containing each landmark's centre (GSMN).
- landmark_cell_c (B, T, M, 2): the image-feature cell (row, col) under each landmark centre's projection
  (first-person baselines; meaningful where visible).
- is_named (B, M): the landmark is the one the instruction names (the grounding label).
- goal_cell_w (B, 2): the world-map cell containing the goal.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from gsmn.model.batch import Batch
from gsmn.model.grid import MapGeometry
from gsmn.model.perception import DOWNSCALE
from gsmn.model.projection import invert_rigid


@dataclass(frozen=True)
class Labels:
    visible: torch.Tensor  # (B, T, M) bool
    landmark_cell_w: torch.Tensor  # (B, M, 2) int64 (row, col)
    landmark_cell_c: torch.Tensor  # (B, T, M, 2) int64 (row, col)
    is_named: torch.Tensor  # (B, M) bool
    goal_cell_w: torch.Tensor  # (B, 2) int64 (row, col)


def project_landmarks(batch: Batch) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates (B, T, M, 2) and depths (B, T, M) of the landmark centres on the ground."""
    points_w = torch.cat([batch.landmark_xy, torch.zeros_like(batch.landmark_xy[..., :1])], dim=-1)  # (B, M, 3)
    T_camera_world = invert_rigid(batch.T_world_camera)  # (B, T, 4, 4)
    p_c = torch.einsum("btij,bmj->btmi", T_camera_world[..., :3, :3], points_w) \
        + T_camera_world[:, :, None, :3, 3]  # (B, T, M, 3)
    uvw = torch.einsum("bij,btmj->btmi", batch.K, p_c)
    depth = p_c[..., 2]
    uv = uvw[..., :2] / torch.where(depth > 1e-6, depth, torch.ones_like(depth))[..., None]
    return uv, depth


def make_labels(batch: Batch, geometry: MapGeometry, image_size: tuple[int, int]) -> Labels:
    """All labels of a batch; image_size is (W, H) in pixels."""
    W, H = image_size
    uv, depth = project_landmarks(batch)
    inside = (depth > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < W) & (uv[..., 1] >= 0) & (uv[..., 1] < H)
    visible = inside & batch.landmark_valid[:, None, :] & batch.mask[:, :, None]
    col = torch.floor(uv[..., 0] / DOWNSCALE).clamp(0, W // DOWNSCALE - 1)
    row = torch.floor(uv[..., 1] / DOWNSCALE).clamp(0, H // DOWNSCALE - 1)
    M = batch.landmark_xy.shape[1]
    is_named = torch.arange(M, device=batch.named_landmark.device)[None, :] == batch.named_landmark[:, None]
    return Labels(visible=visible, landmark_cell_w=geometry.world_cell_of(batch.landmark_xy),
                  landmark_cell_c=torch.stack([row, col], dim=-1).long(), is_named=is_named & batch.landmark_valid,
                  goal_cell_w=geometry.world_cell_of(batch.goal_xy))
