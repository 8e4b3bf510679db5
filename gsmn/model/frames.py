"""World frame to robot frame and back (paper: Language Grounding and Goal Prediction: "we compute R_r by
transforming R_w to the agent reference frame"; original code: affine_grid + grid_sample into a 64x64
egocentric map at the same resolution).

Layouts are in `gsmn.model.grid`: in the robot map the drone sits at the centre facing up (row 0 ahead,
column 0 on its left). Resampling is bilinear; robot-map cells that fall outside the field read zeros. The
64x64 robot map reaches 30 m ahead, behind and to each side: from a start corner facing the diagonal, the far
corner of the field (42 m away) is cut off. `robot_to_world` is the inverse transform (the world-frame copy of
the goal map); a round trip is exact up to bilinear resampling.

The grid_sample matrices are the products of the named transforms in `gsmn.model.grid`
(normalised_from_world @ world_from_robot(pose) @ robot_from_normalised and its inverse); written out, both are
linear in the pose features f = [c, s, x, y, 1, c x, c y, s x, s y] (c, s = cos, sin of the yaw), so one small
matmul gives them (tests check them against the products). With a = 2 R / F (R the robot map's half extent,
F the field size):

    world <- robot: [[a s, -a c, 2 x / F - 1],
                     [a c,  a s, 1 - 2 y / F]]
    robot <- world: [[ s / a, c / a, (s - c) / a - 2 (s x - c y) / (a F)],
                     [-c / a, s / a, 2 (c x + s y) / (a F) - (c + s) / a]]
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from gsmn.model.grid import MapGeometry


def _theta_matrix(geometry: MapGeometry) -> torch.Tensor:
    """(9, 12): pose features f -> [world<-robot theta (6), robot<-world theta (6)], row-major 2x3 each."""
    a, Fs = 2 * geometry.robot_half_extent / geometry.field_size, geometry.field_size
    M = torch.zeros(9, 12, dtype=torch.float64)
    c, s, x, y, one, cx, cy, sx, sy = range(9)
    # world <- robot
    M[s, 0], M[c, 1], M[x, 2], M[one, 2] = a, -a, 2 / Fs, -1.0
    M[c, 3], M[s, 4], M[y, 5], M[one, 5] = a, a, -2 / Fs, 1.0
    # robot <- world
    M[s, 6], M[c, 7], M[s, 8], M[c, 8], M[sx, 8], M[cy, 8] = 1 / a, 1 / a, 1 / a, -1 / a, -2 / (a * Fs), 2 / (a * Fs)
    M[c, 9], M[s, 10], M[c, 11], M[s, 11] = -1 / a, 1 / a, -1 / a, -1 / a
    M[cx, 11], M[sy, 11] = 2 / (a * Fs), 2 / (a * Fs)
    return M.float()


def _pose_features(poses: torch.Tensor) -> torch.Tensor:
    """(N, 9) features [c, s, x, y, 1, c x, c y, s x, s y] of poses (N, 3) = x, y, yaw."""
    x, y, yaw = poses.unbind(-1)
    c, s = torch.cos(yaw), torch.sin(yaw)
    return torch.stack([c, s, x, y, torch.ones_like(x), c * x, c * y, s * x, s * y], dim=-1)


def _base_grid(size: int) -> torch.Tensor:
    """(size*size, 3) homogeneous grid_sample coordinates [x, y, 1] of an output map's cell centres
    (align_corners=False), row-major: what affine_grid multiplies by theta."""
    t = (2 * torch.arange(size, dtype=torch.float32) + 1) / size - 1
    gy, gx = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([gx, gy, torch.ones_like(gx)], dim=-1).reshape(-1, 3)


class FrameTransform(nn.Module):
    """World <-> robot resampling for one map geometry, with its constant matrices cached as buffers."""

    def __init__(self, geometry: MapGeometry):
        super().__init__()
        self.geometry = geometry
        self.register_buffer("theta_matrix", _theta_matrix(geometry), persistent=False)  # (9, 12)
        self.register_buffer("robot_grid", _base_grid(geometry.robot_map_size), persistent=False)
        self.register_buffer("world_grid", _base_grid(geometry.map_size), persistent=False)

    def thetas(self, poses: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 2, 3) grid_sample matrices for poses (N, 3): world <- robot and robot <- world."""
        t = _pose_features(poses) @ self.theta_matrix  # (N, 12)
        return t[:, :6].view(-1, 2, 3), t[:, 6:].view(-1, 2, 3)

    @staticmethod
    def _resample(maps: torch.Tensor, theta: torch.Tensor, base: torch.Tensor, size: int) -> torch.Tensor:
        grid = (base @ theta.transpose(1, 2)).view(-1, size, size, 2)  # (N, size, size, 2), as affine_grid
        return F.grid_sample(maps, grid, mode="bilinear", padding_mode="zeros", align_corners=False)

    def to_robot(self, map_w: torch.Tensor, theta_world_robot: torch.Tensor) -> torch.Tensor:
        """World maps (N, C, n, n) -> robot maps (N, C, 2n, 2n), given the first matrix of `thetas(poses)`."""
        return self._resample(map_w, theta_world_robot, self.robot_grid, self.geometry.robot_map_size)

    def to_world(self, map_r: torch.Tensor, theta_robot_world: torch.Tensor) -> torch.Tensor:
        """Robot maps (N, C, 2n, 2n) -> world maps (N, C, n, n), given the second matrix of `thetas(poses)`."""
        return self._resample(map_r, theta_robot_world, self.world_grid, self.geometry.map_size)

    def world_to_robot(self, map_w: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """World maps (N, C, n, n) -> robot maps (N, C, 2n, 2n) around poses (N, 3) = x, y, yaw."""
        return self.to_robot(map_w, self.thetas(poses)[0])

    def robot_to_world(self, map_r: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """Robot maps (N, C, 2n, 2n) -> world maps (N, C, n, n)."""
        return self.to_world(map_r, self.thetas(poses)[1])


def world_to_robot_theta(poses: torch.Tensor, geometry: MapGeometry) -> torch.Tensor:
    """(N, 2, 3) affine_grid matrices: robot-map grid coordinates -> world-map grid coordinates."""
    return (_pose_features(poses) @ _theta_matrix(geometry).to(poses))[:, :6].view(-1, 2, 3)


def robot_to_world_theta(poses: torch.Tensor, geometry: MapGeometry) -> torch.Tensor:
    """(N, 2, 3) affine_grid matrices: world-map grid coordinates -> robot-map grid coordinates."""
    return (_pose_features(poses) @ _theta_matrix(geometry).to(poses))[:, 6:].view(-1, 2, 3)


def world_to_robot(map_w: torch.Tensor, poses: torch.Tensor, geometry: MapGeometry) -> torch.Tensor:
    """Resample world maps (N, C, n, n) into robot maps (N, C, 2n, 2n) around poses (N, 3) = x, y, yaw."""
    return FrameTransform(geometry).to(map_w).world_to_robot(map_w, poses)


def robot_to_world(map_r: torch.Tensor, poses: torch.Tensor, geometry: MapGeometry) -> torch.Tensor:
    """Resample robot maps (N, C, 2n, 2n) back into world maps (N, C, n, n)."""
    return FrameTransform(geometry).to(map_r).robot_to_world(map_r, poses)
