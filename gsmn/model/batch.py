"""The training data interface: episodes as training reads them, and their padded batches.

The data store produces `EpisodeSample`s (one episode: world, instruction, and per step the image, the camera
pose, the drone pose and the expert's normalised action labels). `collate` pads a list of them into a `Batch`
of tensors (B, T, ...) with a (B, T) validity mask, the instruction's token ids, and what the auxiliary
losses need from the WorldSpec and the instruction (paper: Auxiliary Objectives): landmark positions and
classes, the named landmark, the side, the goal.

Padding repeats an episode's last step rather than writing zeros, so padded steps stay well-formed (an
invertible T_world_camera, a real image) and the model needs no special case; the mask drops them from
every loss.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np
import torch

from gsmn.model.vocabulary import Vocabulary
from gsmn.task.instructions import SIDES, Instruction
from gsmn.world.spec import WorldSpec


@dataclass(frozen=True)
class EpisodeSample:
    """One episode as training reads it."""

    world: WorldSpec
    instruction: Instruction
    images: np.ndarray  # (T, H, W, 3) uint8
    T_world_camera: np.ndarray  # (T, 4, 4) float32
    K: np.ndarray  # (3, 3) float32
    poses: np.ndarray  # (T, 3) float32: drone x, y, yaw
    actions: np.ndarray  # (T, 3) float32: expert v_norm, omega_norm, stop (0/1) labels

    def __post_init__(self) -> None:
        T = len(self.images)
        if T < 1:
            raise ValueError("an episode needs at least one step")
        if self.images.ndim != 4 or self.images.shape[3] != 3 or self.images.dtype != np.uint8:
            raise ValueError(f"images must be (T, H, W, 3) uint8, got {self.images.shape} {self.images.dtype}")
        for name, shape in (("T_world_camera", (T, 4, 4)), ("poses", (T, 3)), ("actions", (T, 3)),
                            ("K", (3, 3))):
            if getattr(self, name).shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {getattr(self, name).shape}")

    @property
    def length(self) -> int:
        return len(self.images)


@dataclass(frozen=True)
class Batch:
    """Padded episodes. B episodes, T steps (the longest), L tokens (the longest), M landmarks (the most)."""

    images: torch.Tensor  # (B, T, H, W, 3) uint8
    T_world_camera: torch.Tensor  # (B, T, 4, 4) float32, true camera poses
    K: torch.Tensor  # (B, 3, 3) float32
    poses: torch.Tensor  # (B, T, 3) float32, true drone x, y, yaw
    actions: torch.Tensor  # (B, T, 3) float32, expert v_norm, omega_norm, stop
    mask: torch.Tensor  # (B, T) bool, True at real (not padded) steps
    tokens: torch.Tensor  # (B, L) int64, PAD after the end
    lengths: torch.Tensor  # (B,) int64, >= 1
    landmark_xy: torch.Tensor  # (B, M, 2) float32, landmark centres in the world frame
    landmark_class: torch.Tensor  # (B, M) int64, index into gsmn.world.landmarks.CATALOGUE
    landmark_valid: torch.Tensor  # (B, M) bool, False for padding
    named_landmark: torch.Tensor  # (B,) int64, index into the M landmarks: the one the instruction names
    side: torch.Tensor  # (B,) int64, index into gsmn.task.instructions.SIDES
    goal_xy: torch.Tensor  # (B, 2) float32

    @property
    def size(self) -> int:
        return self.images.shape[0]

    @property
    def steps(self) -> int:
        return self.images.shape[1]

    @property
    def frames(self) -> int:
        """Real (unpadded) steps in the batch."""
        return int(self.mask.sum())

    @property
    def named_class(self) -> torch.Tensor:
        """(B,) class of the named landmark."""
        return self.landmark_class.gather(1, self.named_landmark[:, None])[:, 0]

    def to(self, device: torch.device | str) -> Batch:
        return Batch(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})


def _pad_steps(x: np.ndarray, T: int) -> np.ndarray:
    """Pad axis 0 to length T by repeating the last entry."""
    if len(x) == T:
        return x
    return np.concatenate([x, np.repeat(x[-1:], T - len(x), axis=0)])


def collate(samples: Sequence[EpisodeSample], vocabulary: Vocabulary) -> Batch:
    """Pad episodes into one Batch (see the module docstring for the padding rule)."""
    if not samples:
        raise ValueError("collate needs at least one episode")
    B = len(samples)
    T = max(s.length for s in samples)
    M = max(len(s.world.landmarks) for s in samples)
    token_ids = [vocabulary.encode(s.instruction.text) for s in samples]
    L = max(len(t) for t in token_ids)

    tokens = np.full((B, L), vocabulary.pad_id, dtype=np.int64)
    landmark_xy = np.zeros((B, M, 2), dtype=np.float32)
    landmark_class = np.zeros((B, M), dtype=np.int64)
    landmark_valid = np.zeros((B, M), dtype=bool)
    mask = np.zeros((B, T), dtype=bool)
    for b, s in enumerate(samples):
        tokens[b, :len(token_ids[b])] = token_ids[b]
        mask[b, :s.length] = True
        for m, lm in enumerate(s.world.landmarks):
            landmark_xy[b, m] = (lm.x, lm.y)
            landmark_class[b, m] = lm.class_id
            landmark_valid[b, m] = True

    def steps(name: str, dtype: type) -> torch.Tensor:
        return torch.from_numpy(np.stack([_pad_steps(getattr(s, name), T) for s in samples]).astype(dtype))

    return Batch(
        images=steps("images", np.uint8),
        T_world_camera=steps("T_world_camera", np.float32),
        K=torch.from_numpy(np.stack([s.K for s in samples]).astype(np.float32)),
        poses=steps("poses", np.float32),
        actions=steps("actions", np.float32),
        mask=torch.from_numpy(mask),
        tokens=torch.from_numpy(tokens),
        lengths=torch.tensor([len(t) for t in token_ids], dtype=torch.int64),
        landmark_xy=torch.from_numpy(landmark_xy),
        landmark_class=torch.from_numpy(landmark_class),
        landmark_valid=torch.from_numpy(landmark_valid),
        named_landmark=torch.tensor([s.instruction.landmark_index for s in samples], dtype=torch.int64),
        side=torch.tensor([SIDES.index(s.instruction.side) for s in samples], dtype=torch.int64),
        goal_xy=torch.tensor([[s.instruction.goal_x, s.instruction.goal_y] for s in samples], dtype=torch.float32),
    )
