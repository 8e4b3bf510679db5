"""Map geometry: which world point each map cell stands for (paper: Feature Projection, Semantic Map).

World-frame maps (`_w`) cover the field [0, F]^2 with N x N cells (F = 30 m, N = 32: 0.9375 m cells) and are
laid out as a north-up picture: row 0 is the north edge (y = F), column 0 the west edge (x = 0), so cell
(r, c) has its centre at x = (c + 0.5) s, y = F - (r + 0.5) s with s = F / N.

Robot-frame maps (`_r`) have the same cell size, 2N x 2N cells (60 m across, so the whole field fits from
anywhere in it), the drone at the centre (the corner shared by the four middle cells), facing up: row 0 is
straight ahead, column 0 is on the drone's left. In robot coordinates (x forward, y left) cell (r, c) has its
centre at x = (N_r/2 - r - 0.5) s, y = (N_r/2 - c - 0.5) s. A drone heading north (yaw = 90 deg) sees its
robot map as the world map shifted.

Both layouts are addressed with `torch.nn.functional.grid_sample(..., align_corners=False)`, whose
normalised coordinate -1 is the outer edge of the first cell; the matrices below map metric coordinates to
those normalised coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch


def world_cell(x, y, field_size: float, cells: int, floor=math.floor):
    """The (row, col) of the north-up world-map cell holding the point (x, y), not clamped (a point off the map
    gives an index outside [0, cells)). Numbers with `math.floor` (the default), tensors with `torch.floor`."""
    s = field_size / cells
    return floor((field_size - y) / s), floor(x / s)


def cell_of(x: float, y: float, field_size: float, n: int) -> tuple[int, int]:
    """The (row, col) of the north-up world-map cell holding (x, y), clamped into the map."""
    row, col = world_cell(x, y, field_size, n)
    return min(max(row, 0), n - 1), min(max(col, 0), n - 1)


def cell_centre(row: int, col: int, field_size: float, n: int) -> tuple[float, float]:
    """The (x, y) of a north-up world-map cell's centre."""
    s = field_size / n
    return (col + 0.5) * s, field_size - (row + 0.5) * s


def observed_cells(semantic_map_w: np.ndarray) -> np.ndarray:
    """(n, n) bool: cells the camera covered at some step (never-covered cells hold exactly zero)."""
    return np.abs(semantic_map_w.astype(np.float32)).max(0) > 1e-6


@dataclass(frozen=True)
class MapGeometry:
    field_size: float  # F, metres
    map_size: int  # world map cells per side
    robot_map_size: int  # robot map cells per side

    @property
    def cell_size(self) -> float:
        return self.field_size / self.map_size

    @property
    def robot_half_extent(self) -> float:
        """Metres from the robot map's centre to its edge."""
        return self.robot_map_size * self.cell_size / 2

    def world_cell_centres(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(N, N, 2) world x, y of every world-map cell centre."""
        i = (torch.arange(self.map_size, dtype=dtype) + 0.5) * self.cell_size
        y = self.field_size - i  # row r -> y = F - (r + 0.5) s
        return torch.stack(torch.meshgrid(i, y, indexing="xy"), dim=-1)

    def world_cell_of(self, xy: torch.Tensor) -> torch.Tensor:
        """(..., 2) integer (row, col) of the world cell containing each point, clamped into the map."""
        row, col = world_cell(xy[..., 0], xy[..., 1], self.field_size, self.map_size, torch.floor)
        rc = torch.stack([row, col], dim=-1).clamp(0, self.map_size - 1)
        return rc.long()

    def normalised_from_world(self, like: torch.Tensor) -> torch.Tensor:
        """(3, 3) homogeneous map from world x, y to the world map's grid_sample coordinates."""
        F = self.field_size
        return like.new_tensor([[2 / F, 0.0, -1.0], [0.0, -2 / F, 1.0], [0.0, 0.0, 1.0]])

    def world_from_normalised(self, like: torch.Tensor) -> torch.Tensor:
        """(3, 3) inverse of `normalised_from_world`."""
        F = self.field_size
        return like.new_tensor([[F / 2, 0.0, F / 2], [0.0, -F / 2, F / 2], [0.0, 0.0, 1.0]])

    def normalised_from_robot(self, like: torch.Tensor) -> torch.Tensor:
        """(3, 3) homogeneous map from robot x (forward), y (left) to the robot map's grid_sample coordinates."""
        R = self.robot_half_extent
        return like.new_tensor([[0.0, -1 / R, 0.0], [-1 / R, 0.0, 0.0], [0.0, 0.0, 1.0]])

    def robot_from_normalised(self, like: torch.Tensor) -> torch.Tensor:
        """(3, 3) homogeneous map from the robot map's grid_sample coordinates to robot x (forward), y (left)."""
        R = self.robot_half_extent
        return like.new_tensor([[0.0, -R, 0.0], [-R, 0.0, 0.0], [0.0, 0.0, 1.0]])


def world_from_robot(poses: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) homogeneous 2D transforms from robot coordinates to world x, y, for poses (..., 3) = x, y, yaw."""
    x, y, yaw = poses.unbind(-1)
    c, s = torch.cos(yaw), torch.sin(yaw)
    zero, one = torch.zeros_like(x), torch.ones_like(x)
    rows = [torch.stack([c, -s, x], -1), torch.stack([s, c, y], -1), torch.stack([zero, zero, one], -1)]
    return torch.stack(rows, dim=-2)


def invert_rigid_2d(T: torch.Tensor) -> torch.Tensor:
    """Inverse of (..., 3, 3) rotation-plus-translation transforms."""
    R, t = T[..., :2, :2], T[..., :2, 2:]
    Rt = R.transpose(-1, -2)
    top = torch.cat([Rt, -Rt @ t], dim=-1)
    return torch.cat([top, T[..., 2:, :]], dim=-2)
