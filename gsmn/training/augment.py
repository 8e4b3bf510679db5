"""Mirror augmentation: an episode reflected east-west, as if flown in the mirror image of its world.

Not in the paper or the original code (docs/design.md, "Mirrored episodes"). The reflection itself (worlds,
instructions, cameras, observations) is `gsmn.task.mirror`; here whole training episodes are reflected: the
images flipped left to right, poses and camera transforms reflected, yaw-rate labels negated, "left" and "right"
swapped in the instruction. The augmentation sees new images and, mainly, teaches left and right from the same
episodes: the training set's left-side episodes also train "right", and the other way round.
"""

from __future__ import annotations

import numpy as np

from gsmn.model.batch import EpisodeSample
from gsmn.task.mirror import mirror_camera, mirror_instruction, mirror_world, mirror_yaw


def mirror_episode(sample: EpisodeSample) -> EpisodeSample:
    """The episode as flown in the mirrored world (see the module docstring)."""
    F = sample.world.field_size
    poses = sample.poses.copy()
    poses[:, 0] = F - poses[:, 0]
    poses[:, 2] = mirror_yaw(poses[:, 2])
    actions = sample.actions.copy()
    actions[:, 1] = -actions[:, 1]
    return EpisodeSample(world=mirror_world(sample.world), instruction=mirror_instruction(sample.instruction, F),
                         images=np.ascontiguousarray(sample.images[:, :, ::-1]),
                         T_world_camera=mirror_camera(sample.T_world_camera, F), K=sample.K, poses=poses,
                         actions=actions)


def maybe_mirror(samples: list[EpisodeSample], probability: float, seed: int, positions: list[int] | None = None,
                 count: int | None = None) -> list[EpisodeSample]:
    """Each episode mirrored with `probability`, the draws seeded (a resumed run mirrors the same ones). With
    `positions`, the samples are those places of a batch of `count` (a rank's shard) and take those places' draws."""
    if probability <= 0:
        return samples
    draws = np.random.default_rng(np.random.SeedSequence([seed, 0x6D6972])).random(
        len(samples) if positions is None else count)
    if positions is not None:
        draws = draws[positions]
    return [mirror_episode(s) if u < probability else s for s, u in zip(samples, draws, strict=True)]
