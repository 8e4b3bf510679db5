"""The east-west reflection of a world and of everything flown in it (x -> F - x, F the field size).

Used twice: to augment training episodes (`gsmn.training.augment`, docs/design.md "Mirrored episodes") and by
the test-time mirror ensemble (`gsmn.model.policy.MirrorEnsemble`, docs/design.md "Mirror ensemble"). Neither is
in the paper or the original code. The reflection maps a world onto another valid one:

- every landmark, lake, goal and drone position: x -> F - x; headings and yaws: yaw -> pi - yaw;
- the camera: T' = A T C with A the world reflection and C = diag(-1, 1, 1) flipping the camera's x axis (image
  right), so T' is again a rigid transform and the camera sees the mirror image: the images are flipped left to
  right (exact for a pinhole camera whose principal point is the image centre, as `gsmn.world.sim.intrinsics`);
- actions: forward speed and STOP unchanged, yaw rate negated;
- the instruction: sides are taken from the start, whose reflection flips handedness, so "left" and "right"
  swap (front and back stay); the goal is the reflected goal (the same as `goal_position` of the mirrored world
  and the swapped side, tested).

What a mirrored camera shows is the mirror image of each landmark model (the meshes are not mirror-symmetric),
lit from the mirrored sun; the class labels stay.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gsmn.task.expert import wrap_angle
from gsmn.task.instructions import Instruction, tokenize
from gsmn.task.rollout import Task
from gsmn.world.env import Observation, Pose
from gsmn.world.spec import WorldSpec

SWAPPED_SIDES = {"left": "right", "right": "left"}
_FLIP_X = np.diag([-1.0, 1.0, 1.0])
_FLIP_Y = np.diag([1.0, -1.0, 1.0])


def mirror_yaw(yaw: float | np.ndarray) -> float | np.ndarray:
    """pi - yaw, wrapped (elementwise for arrays, keeping their dtype)."""
    return wrap_angle(np.pi - yaw)


def mirror_world(world: WorldSpec) -> WorldSpec:
    """The world reflected about x = F / 2 (the start corner's index is the reflected corner's)."""
    F = world.field_size
    corner = {0: 1, 1: 0, 2: 3, 3: 2}[world.start_corner]
    return replace(
        world, landmarks=tuple(replace(lm, x=F - lm.x, yaw=mirror_yaw(lm.yaw)) for lm in world.landmarks),
        lakes=tuple(replace(lake, x=F - lake.x, yaw=mirror_yaw(lake.yaw)) for lake in world.lakes),
        start_corner=corner, start_x=F - world.start_x, start_yaw=mirror_yaw(world.start_yaw))


def mirror_text(text: str) -> str:
    """The instruction's words with "left" and "right" swapped (tokenised, as the model reads it)."""
    return " ".join(SWAPPED_SIDES.get(w, w) for w in tokenize(text))


def mirror_instruction(instruction: Instruction, field_size: float) -> Instruction:
    """The instruction in the mirrored world: left and right swapped in its side and text, its goal reflected."""
    return replace(instruction, text=mirror_text(instruction.text),
                   side=SWAPPED_SIDES.get(instruction.side, instruction.side), goal_x=field_size - instruction.goal_x)


def mirror_task(task: Task) -> Task:
    """The task in the mirrored world: world and instruction mirrored, the demonstration path reflected."""
    F = task.world.field_size
    path = np.array(task.path, dtype=np.float64, copy=True)
    path[:, 0] = F - path[:, 0]
    return Task(mirror_world(task.world), mirror_instruction(task.instruction, F), path)


def mirror_camera(T_world_camera: np.ndarray, field_size: float) -> np.ndarray:
    """(..., 4, 4) camera-to-world transforms of the mirrored flight: A @ T @ C (see the module docstring)."""
    A = np.diag([-1.0, 1.0, 1.0, 1.0])
    A[0, 3] = field_size
    C = np.diag([-1.0, 1.0, 1.0, 1.0])
    return (A @ T_world_camera.astype(np.float64) @ C).astype(T_world_camera.dtype)


def mirror_observation(obs: Observation, field_size: float) -> Observation:
    """What the drone would observe at the mirrored pose in the mirrored world: the image flipped left to right,
    the position and yaw reflected, the body's y axis (left) flipped, the camera A T C; K unchanged."""
    p = obs.pose.position.copy()
    p[0] = field_size - p[0]
    pose = Pose(position=p, yaw=float(mirror_yaw(obs.pose.yaw)),
                R_world_body=_FLIP_X @ obs.pose.R_world_body @ _FLIP_Y)
    image = None if obs.image is None else np.ascontiguousarray(obs.image[:, ::-1])
    return replace(obs, image=image, pose=pose, T_world_camera=mirror_camera(obs.T_world_camera, field_size))
