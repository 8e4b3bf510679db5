"""Ground projection of image features into the world map (paper: Feature Projection).

Backward mapping, as the original code: every world-map cell centre (x, y, 0) on the ground plane is projected
through the pinhole camera (K, T_world_camera) into the image, and the feature map is sampled there
bilinearly. Cells behind the camera or outside the image read zeros; the coverage mask is the same
projection of an all-ones feature map (1 inside the view, 0 outside, fractional along the image border).

Pixel conventions (docs/design.md): pixel (u, v) has the centre of the top-left pixel at (0.5, 0.5), so u runs
over [0, W] across the image. Feature cell (i, j) covers pixels [8j, 8j + 8) x [8i, 8i + 8), so the feature map
spans the same [0, W] x [0, H] and grid_sample's normalised coordinate (align_corners=False, -1 at the outer
edge of the first cell) is simply 2 u / W - 1, 2 v / H - 1, independent of the downscale factor.

Only the features get gradients; the geometry is fixed given the pose (paper: "the transformations
themselves are not learned").
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from gsmn.model.grid import MapGeometry

# Points closer than this in front of the camera count as behind it (their projection is unbounded).
_MIN_DEPTH = 1e-3
# grid_sample coordinate for cells that must read zero: outside [-1, 1] by more than a cell.
_OUTSIDE = -4.0


def invert_rigid(T: torch.Tensor) -> torch.Tensor:
    """Inverse of (..., 4, 4) rigid transforms."""
    R, t = T[..., :3, :3], T[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    return torch.cat([torch.cat([Rt, -Rt @ t], dim=-1), T[..., 3:, :]], dim=-2)


def ground_points(geometry: MapGeometry) -> torch.Tensor:
    """(n*n, 4) homogeneous world coordinates [x, y, 0, 1] of the world-map cell centres on the ground, row-major."""
    centres = geometry.world_cell_centres().reshape(-1, 2)
    return torch.cat([centres, torch.zeros_like(centres[:, :1]), torch.ones_like(centres[:, :1])], dim=-1)


def ground_grid(T_world_camera: torch.Tensor, K: torch.Tensor, geometry: MapGeometry, image_size: tuple[int, int],
                points_w: torch.Tensor | None = None) -> torch.Tensor:
    """grid_sample coordinates (N, n, n, 2) in the image of every world-map cell centre on the ground.

    T_world_camera (N, 4, 4), K (N, 3, 3), image_size (W, H) in pixels; `points_w` caches `ground_points`.
    Cells behind the camera get a coordinate far outside the image."""
    W, H = image_size
    if points_w is None:
        points_w = ground_points(geometry).to(T_world_camera)
    n = geometry.map_size
    # The camera matrix K [R^T | -R^T t] with K's rows scaled to grid_sample units (u -> 2 u / W), (N, 3, 4)
    P = (K * K.new_tensor([[2.0 / W], [2.0 / H], [1.0]])) @ invert_rigid(T_world_camera)[:, :3, :]
    uvw = points_w @ P.transpose(1, 2)  # (N, n*n, 3); uvw[..., 2] is the depth along the optical axis
    depth = uvw[..., 2:]
    grid = (uvw[..., :2] / depth - 1.0).clamp(-2 * abs(_OUTSIDE), 2 * abs(_OUTSIDE))  # inf or NaN behind: replaced
    grid = torch.where(depth > _MIN_DEPTH, grid, _OUTSIDE)
    return grid.view(-1, n, n, 2)


def project_to_ground(features_c: torch.Tensor, T_world_camera: torch.Tensor, K: torch.Tensor,
                      geometry: MapGeometry, image_size: tuple[int, int], points_w: torch.Tensor | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Project feature maps (N, C, h, w) onto the ground.

    Returns projected_features_w (N, C, n, n) and coverage_w (N, 1, n, n)."""
    with torch.no_grad():
        grid = ground_grid(T_world_camera.float(), K.float(), geometry, image_size, points_w)
    projected_w = F.grid_sample(features_c, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    ones = features_c.new_ones(features_c.shape[0], 1, *features_c.shape[2:])
    coverage_w = F.grid_sample(ones, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return projected_w, coverage_w
