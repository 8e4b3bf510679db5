"""Mirror augmentation: an episode reflected east-west, as if flown in the mirror image of its world.

Not in the paper or the original code (docs/design.md, "Mirrored episodes"). The reflection x -> F - x (F the
field size) maps a world and everything flown in it onto another valid one:

- every landmark, lake, goal and drone position: x -> F - x; headings and yaws: yaw -> pi - yaw;
- the camera: T' = A T C with A the world reflection and C = diag(-1, 1, 1) flipping the camera's x axis (image
  right), so T' is again a rigid transform and the camera sees the mirror image: the images are flipped left to
  right (exact for a pinhole camera whose principal point is the image centre, as `gsmn.world.sim.intrinsics`);
- the expert's actions: forward speed and STOP unchanged, yaw rate negated;
- the instruction: sides are taken from the start, whose reflection flips handedness, so "left" and "right"
  swap (front and back stay); the goal is the reflected goal (the same as `goal_position` of the mirrored world
  and the swapped side, tested).

What the images show is the mirror image of each landmark model (the meshes are not mirror-symmetric), lit from
the mirrored sun; the class labels stay. The augmentation sees new images and, mainly, teaches left and right from
the same episodes: the training set's left-side episodes also train "right", and the other way round.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gsmn.model.batch import EpisodeSample
from gsmn.task.expert import wrap_angle
from gsmn.task.instructions import Instruction, tokenize
from gsmn.world.spec import WorldSpec

SWAPPED_SIDES = {"left": "right", "right": "left"}


def _yaw(yaw: float | np.ndarray) -> float | np.ndarray:
    """pi - yaw, wrapped (elementwise for arrays, keeping their dtype)."""
    return wrap_angle(np.pi - yaw)


def mirror_world(world: WorldSpec) -> WorldSpec:
    """The world reflected about x = F / 2 (the start corner's index is the reflected corner's)."""
    F = world.field_size
    corner = {0: 1, 1: 0, 2: 3, 3: 2}[world.start_corner]
    return replace(
        world, landmarks=tuple(replace(lm, x=F - lm.x, yaw=_yaw(lm.yaw)) for lm in world.landmarks),
        lakes=tuple(replace(lake, x=F - lake.x, yaw=_yaw(lake.yaw)) for lake in world.lakes),
        start_corner=corner, start_x=F - world.start_x, start_yaw=_yaw(world.start_yaw))


def mirror_text(text: str) -> str:
    """The instruction's words with "left" and "right" swapped (tokenised, as the model reads it)."""
    return " ".join(SWAPPED_SIDES.get(w, w) for w in tokenize(text))


def mirror_instruction(instruction: Instruction, field_size: float) -> Instruction:
    """The instruction in the mirrored world: left and right swapped in its side and text, its goal reflected."""
    return replace(instruction, text=mirror_text(instruction.text),
                   side=SWAPPED_SIDES.get(instruction.side, instruction.side), goal_x=field_size - instruction.goal_x)


def mirror_camera(T_world_camera: np.ndarray, field_size: float) -> np.ndarray:
    """(..., 4, 4) camera-to-world transforms of the mirrored flight: A @ T @ C (see the module docstring)."""
    A = np.diag([-1.0, 1.0, 1.0, 1.0])
    A[0, 3] = field_size
    C = np.diag([-1.0, 1.0, 1.0, 1.0])
    return (A @ T_world_camera.astype(np.float64) @ C).astype(T_world_camera.dtype)


def mirror_episode(sample: EpisodeSample) -> EpisodeSample:
    """The episode as flown in the mirrored world (see the module docstring)."""
    F = sample.world.field_size
    poses = sample.poses.copy()
    poses[:, 0] = F - poses[:, 0]
    poses[:, 2] = _yaw(poses[:, 2])
    actions = sample.actions.copy()
    actions[:, 1] = -actions[:, 1]
    return EpisodeSample(world=mirror_world(sample.world), instruction=mirror_instruction(sample.instruction, F),
                         images=np.ascontiguousarray(sample.images[:, :, ::-1]),
                         T_world_camera=mirror_camera(sample.T_world_camera, F), K=sample.K, poses=poses,
                         actions=actions)


def maybe_mirror(samples: list[EpisodeSample], probability: float, seed: int) -> list[EpisodeSample]:
    """Each episode mirrored with `probability`, the draws seeded (a resumed run mirrors the same ones)."""
    if probability <= 0:
        return samples
    draws = np.random.default_rng(np.random.SeedSequence([seed, 0x6D6972])).random(len(samples))
    return [mirror_episode(s) if u < probability else s for s, u in zip(samples, draws, strict=True)]
