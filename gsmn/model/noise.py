"""Pose noise (paper: Systems, the GSMN + eta_pos experiment; original code: std 0.5 m, optionally yaw noise).

Fresh Gaussian noise on the position (x, y, z) and optionally the yaw the model is told, drawn on every
forward pass. The same noisy pose feeds the ground projection (T_world_camera) and the world-to-robot frame
change (x, y, yaw). The labels of the auxiliary objectives keep using the true poses.
"""

from __future__ import annotations

import math

import torch


def perturb_poses(poses: torch.Tensor, T_world_camera: torch.Tensor, position_std: float, yaw_std_deg: float,
                  generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Noisy copies of poses (..., 3) = x, y, yaw and camera poses (..., 4, 4); the inputs are left unchanged.

    The camera moves with the drone: shifted by the position noise and turned by the yaw noise about the
    vertical axis through the drone."""
    if position_std == 0 and yaw_std_deg == 0:
        return poses, T_world_camera
    shape = poses.shape[:-1]
    eta = torch.randn(*shape, 3, generator=generator, dtype=poses.dtype, device=poses.device) * position_std
    eta_yaw = torch.randn(*shape, generator=generator, dtype=poses.dtype, device=poses.device) \
        * math.radians(yaw_std_deg)
    noisy_poses = poses + torch.cat([eta[..., :2], eta_yaw[..., None]], dim=-1)
    c, s = torch.cos(eta_yaw), torch.sin(eta_yaw)
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    Rz = torch.stack([torch.stack([c, -s, zero], -1), torch.stack([s, c, zero], -1),
                      torch.stack([zero, zero, one], -1)], dim=-2)  # (..., 3, 3)
    p = torch.cat([poses[..., :2], torch.zeros_like(poses[..., :1])], dim=-1)  # drone position on the axis
    T = T_world_camera.clone()
    T[..., :3, :3] = Rz @ T_world_camera[..., :3, :3]
    T[..., :3, 3] = (Rz @ (T_world_camera[..., :3, 3] - p)[..., None])[..., 0] + p + eta
    return noisy_poses, T
