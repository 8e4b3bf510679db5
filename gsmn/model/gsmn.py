"""The Grounded Semantic Mapping Network (paper: Model Architecture, all subsections).

    features_c            = ResNet13(standardise(image))                      Instruction and Image Embedding
    projected_features_w,
    coverage_w            = ground projection through K, T_world_camera       Feature Projection
    semantic_map_w        = leaky integrator over the episode                 Semantic Map Accumulation
    relevance_map_w       = LeakyReLU(1x1 language filter * semantic_map_w)   Language Grounding
    relevance_map_r       = relevance_map_w seen from the drone (x, y, yaw)   ... and Goal Prediction
    goal_map_r            = language 3x3 filters (relevance_map_r)
    goal_map_w            = goal_map_r back in the world frame (for J_plan and the dashboard)
    v, omega, stop_logit  = controller([goal_map_r, relevance_map_r])         Control

The original code's -J_ground and -J_goal ablations remove a filter, not only its loss (`model.grounding_filter`,
`model.goal_filter`; docs/model.md, "Removing a module"). As there, the maps form a stack: each filter puts its
output before the channels it read, an identity passes the stack on, and each reader takes the stack's first
channels. Without the grounding filter the "relevance map" is the semantic map's first 3 channels; without the goal
filter the controller reads the stack's first 5 channels in the drone's frame, [R, S_0, S_1] (or S_0..S_4 with
neither filter), and the record's goal maps are the 2 channels it reads after R, where the goal map was.

`forward` takes whole sequences (B, T, ...) and returns a `GSMNOutputs` record of every intermediate map. It is
pure: perception and projection run batched over all B*T steps, only the leaky integrator is sequential. The
step-level pieces serve the policy and the dashboard: `perceive` (image -> updated semantic map, independent of
the instruction) and `ground` (semantic map + pose + instruction -> maps and action), so a new instruction can
be grounded on an existing map without flying again. `step` = `perceive` + `ground`, with the semantic map as
the carried state. The language-conditioned kernels depend on the instruction only: `instruction_kernels` makes
them once, and `ground` and `step` take them instead of remaking them at every step (the policy does this).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields
from typing import Protocol

import torch
import torch.nn as nn

from gsmn.config import ModelConfig, RunConfig
from gsmn.model.controller import MapController, split_actions
from gsmn.model.filters import GoalFilter, InstructionKernels, RelevanceFilter
from gsmn.model.frames import FrameTransform
from gsmn.model.grid import MapGeometry
from gsmn.model.heads import AuxiliaryHeads
from gsmn.model.language import InstructionEncoder
from gsmn.model.noise import perturb_poses
from gsmn.model.perception import ResNet13, standardise
from gsmn.model.projection import ground_points, project_to_ground
from gsmn.model.semantic_map import accumulate, leaky_integrate


class Substitute(Protocol):
    """A map intervention as the model sees it (made by `gsmn.analysis.intervention`): the map to go on with in
    place of the model's own world map `key`, and what that map holds beyond the field (None: not substituted)."""

    def __call__(self, key: str, fresh: torch.Tensor) -> torch.Tensor: ...

    def outside(self, key: str) -> torch.Tensor | None: ...


@dataclass(frozen=True)
class PerceptionOutputs:
    """One step of perception, (B, ...)."""

    features_c: torch.Tensor  # (B, C_f, h, w) image features
    projected_features_w: torch.Tensor  # (B, C_f, n, n)
    coverage_w: torch.Tensor  # (B, 1, n, n)
    semantic_map_w: torch.Tensor  # (B, C_f, n, n)


@dataclass(frozen=True)
class GroundingOutputs:
    """Grounding and control on given semantic maps: (B, ...) or (B, T, ...)."""

    sentence_embedding: torch.Tensor  # (B, E)
    relevance_map_w: torch.Tensor  # (B, [T,] 3, n, n)
    relevance_map_r: torch.Tensor  # (B, [T,] 3, 2n, 2n)
    goal_map_r: torch.Tensor  # (B, [T,] 2, 2n, 2n)
    goal_map_w: torch.Tensor  # (B, [T,] 2, n, n)
    v: torch.Tensor  # (B, [T]) normalised forward velocity in [0, 1]
    omega: torch.Tensor  # (B, [T]) normalised yaw rate in [-1, 1]
    stop_logit: torch.Tensor  # (B, [T]) STOP when sigmoid > 0.5


@dataclass(frozen=True)
class GSMNOutputs:
    """Everything GSMN computes for B episodes of T steps."""

    sentence_embedding: torch.Tensor  # (B, E)
    poses: torch.Tensor  # (B, T, 3) the x, y, yaw the model used (noisy when pose noise is on)
    features_c: torch.Tensor  # (B, T, C_f, h, w)
    projected_features_w: torch.Tensor  # (B, T, C_f, n, n)
    coverage_w: torch.Tensor  # (B, T, 1, n, n)
    semantic_map_w: torch.Tensor  # (B, T, C_f, n, n)
    relevance_map_w: torch.Tensor  # (B, T, 3, n, n)
    relevance_map_r: torch.Tensor  # (B, T, 3, 2n, 2n)
    goal_map_r: torch.Tensor  # (B, T, 2, 2n, 2n)
    goal_map_w: torch.Tensor  # (B, T, 2, n, n)
    v: torch.Tensor  # (B, T)
    omega: torch.Tensor  # (B, T)
    stop_logit: torch.Tensor  # (B, T)

    def maps(self) -> dict[str, torch.Tensor]:
        """The spatial maps by name (fields ending in _c, _w or _r), for viewers."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name[-2:] in ("_c", "_w", "_r")}


def add_shared_modules(module: nn.Module, m: ModelConfig, vocabulary_size: int) -> None:
    """The pieces GSMN shares with the first-person baselines, as `module`'s `encoder`, `resnet`,
    `relevance_filter` and `goal_filter` (same attribute names, so checkpoints keep their keys)."""
    slope = m.leaky_relu_slope
    module.encoder = InstructionEncoder(vocabulary_size, m.word_embedding_dim, m.instruction_hidden)
    module.resnet = ResNet13(m.feature_channels, slope, m.channels_last, m.inference_bf16)
    module.relevance_filter = RelevanceFilter(m.instruction_hidden, m.feature_channels, m.relevance_channels,
                                              m.filter_init_std, slope, m.filter_activation)
    module.goal_filter = GoalFilter(m.instruction_hidden, m.relevance_channels, m.goal_channels, 3,
                                    m.filter_init_std, slope, m.filter_activation)


class GSMN(nn.Module):
    """GSMN for a run config (camera size, field size, model sizes) and a vocabulary size."""

    def __init__(self, config: RunConfig, vocabulary_size: int, kind: str = "gsmn"):
        super().__init__()
        m = config.model
        self.kind = kind
        self.config = config
        self.geometry = MapGeometry(config.world.field_size, m.map_size, m.robot_map_size)
        self.image_size = (config.camera.width, config.camera.height)
        self.leaky_lambda = m.leaky_lambda
        self.register_buffer("ground_points_w", ground_points(self.geometry), persistent=False)  # (n*n, 4)
        self.frames = FrameTransform(self.geometry)
        slope = m.leaky_relu_slope
        add_shared_modules(self, m, vocabulary_size)
        if not m.grounding_filter:
            self.relevance_filter = None  # the original's IdentityMapProcessor: no weights, nothing to learn
        if not m.goal_filter:
            self.goal_filter = None
        self.controller = MapController(m.relevance_channels + m.goal_channels, m.robot_map_size, m.controller_hidden,
                                        m.controller_dropout, m.instruction_hidden * m.controller_uses_instruction,
                                        slope)
        self.heads = AuxiliaryHeads(m.feature_channels, m.relevance_channels, m.goal_channels, m.instruction_hidden,
                                    m.landmark_classes, m.side_classes)

    # -- pieces ---------------------------------------------------------------------------------------------
    def encode_instruction(self, tokens: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """Token ids (B, L), lengths (B,) -> sentence embeddings (B, E)."""
        return self.encoder(tokens, lengths)

    def instruction_kernels(self, sentence_embedding: torch.Tensor) -> InstructionKernels:
        """The relevance and goal filters' kernels for sentence embeddings (B, E)."""
        return InstructionKernels.of(self.relevance_filter, self.goal_filter, sentence_embedding)

    def perturb(self, poses: torch.Tensor, T_world_camera: torch.Tensor, generator: torch.Generator | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """The poses the model sees: with the configured pose noise, else unchanged."""
        m = self.config.model
        return perturb_poses(poses, T_world_camera, m.pose_noise_std, m.pose_noise_yaw_deg, generator)

    def _perceive_frames(self, images: torch.Tensor, T_world_camera: torch.Tensor, K: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Images (N, H, W, 3), poses (N, 4, 4), K (N, 3, 3) -> features_c, projected_features_w, coverage_w."""
        features_c = self.resnet(standardise(images))  # (N, C_f, h, w)
        projected_w, coverage_w = project_to_ground(features_c, T_world_camera, K, self.geometry, self.image_size,
                                                    self.ground_points_w)
        return features_c, projected_w, coverage_w

    def perceive(self, image: torch.Tensor, T_world_camera: torch.Tensor, K: torch.Tensor,
                 prev_semantic_map_w: torch.Tensor | None = None) -> PerceptionOutputs:
        """One step of perception for B drones: image (B, H, W, 3), T_world_camera (B, 4, 4), K (B, 3, 3) or (3, 3),
        the previous semantic map (B, C_f, n, n) or None at an episode's first step."""
        K = K.expand(image.shape[0], 3, 3)
        features_c, projected_w, coverage_w = self._perceive_frames(image, T_world_camera, K)
        semantic_map_w = leaky_integrate(prev_semantic_map_w, projected_w, coverage_w, self.leaky_lambda)
        return PerceptionOutputs(features_c, projected_w, coverage_w, semantic_map_w)

    def ground(self, semantic_map_w: torch.Tensor, poses: torch.Tensor, sentence_embedding: torch.Tensor | None = None,
               tokens: torch.Tensor | None = None, lengths: torch.Tensor | None = None,
               kernels: InstructionKernels | None = None, substitute: Substitute | None = None) -> GroundingOutputs:
        """Ground an instruction on semantic maps (B, [T,] C_f, n, n) seen from poses (B, [T,] 3) = x, y, yaw.

        Give the instruction as its sentence embedding (B, E) or as token ids (B, L) with lengths (B,);
        `kernels`, if given, are `instruction_kernels(sentence_embedding)` made beforehand. `substitute`, if given,
        is a map intervention (`gsmn.analysis.intervention.Substitute`): `substitute(key, map_w)` returns the world
        map the model goes on with in place of its own "relevance_map_w" or "goal_map_w" (GSMN with both filters)."""
        if sentence_embedding is None:
            if tokens is None or lengths is None:
                raise ValueError("ground needs a sentence_embedding or tokens and lengths")
            sentence_embedding = self.encode_instruction(tokens, lengths)
        if kernels is None:
            kernels = self.instruction_kernels(sentence_embedding)
        B, lead = semantic_map_w.shape[0], semantic_map_w.shape[1:-3]
        n_per = int(torch.Size(lead).numel())  # steps per sample (1 without a T dimension)
        m = self.config.model
        if self.relevance_filter is not None:
            relevance_w = self.relevance_filter(semantic_map_w, kernels.relevance)  # (B, [T,] 3, n, n)
            if substitute is not None:
                relevance_w = substitute("relevance_map_w", relevance_w)
            rest_w = semantic_map_w  # the stack after R: the semantic map (the original's cat_out)
        else:  # identity: the stack is the semantic map, and its readers take its first channels
            relevance_w = semantic_map_w[..., :m.relevance_channels, :, :]
            rest_w = semantic_map_w[..., m.relevance_channels:, :, :]
        theta_world_robot, theta_robot_world = self.frames.thetas(poses.reshape(B * n_per, 3))  # both ways at once
        if self.goal_filter is not None:
            relevance_r = self.frames.to_robot(relevance_w.reshape(B * n_per, *relevance_w.shape[-3:]),
                                               theta_world_robot)  # (B*T, 3, 2n, 2n)
            goal_r = self.goal_filter(relevance_r.reshape(B, n_per, *relevance_r.shape[1:]), kernels.goal)
            goal_r = goal_r.reshape(B * n_per, *goal_r.shape[2:])  # (B*T, 2, 2n, 2n)
            goal_w = self.frames.to_world(goal_r, theta_robot_world)  # (B*T, 2, n, n)
            if substitute is not None and substitute.outside("goal_map_w") is not None:
                fill = substitute.outside("goal_map_w")  # beyond the field: the substitute's background
                goal_w = substitute("goal_map_w", goal_w)
                goal_r = self.frames.to_robot(goal_w - fill, theta_world_robot) + fill
            controller_in = torch.cat([goal_r, relevance_r], dim=1)
        else:  # identity: the controller reads the stack's first channels, R then the next goal_channels
            goal_w = rest_w[..., :m.goal_channels, :, :].reshape(B * n_per, m.goal_channels, *rest_w.shape[-2:])
            read_w = torch.cat([relevance_w.reshape(B * n_per, *relevance_w.shape[-3:]), goal_w], dim=1)
            controller_in = self.frames.to_robot(read_w, theta_world_robot)  # (B*T, 5, 2n, 2n)
            relevance_r, goal_r = controller_in.split([m.relevance_channels, m.goal_channels], dim=1)
        extra = None
        if m.controller_uses_instruction:
            extra = sentence_embedding.repeat_interleave(n_per, dim=0)
        raw = self.controller(controller_in, extra)  # (B*T, 3)
        v, omega, stop_logit = split_actions(raw.reshape(B, *lead, 3))

        def unflat(x: torch.Tensor) -> torch.Tensor:
            return x.reshape(B, *lead, *x.shape[1:])

        return GroundingOutputs(sentence_embedding, relevance_w, unflat(relevance_r), unflat(goal_r), unflat(goal_w),
                                v, omega, stop_logit)

    # -- whole sequences -------------------------------------------------------------------------------------
    def forward(self, images: torch.Tensor, T_world_camera: torch.Tensor, K: torch.Tensor, poses: torch.Tensor,
                tokens: torch.Tensor, lengths: torch.Tensor, initial_semantic_map_w: torch.Tensor | None = None,
                generator: torch.Generator | None = None) -> GSMNOutputs:
        """B episodes of T steps: images (B, T, H, W, 3) uint8, T_world_camera (B, T, 4, 4), K (B, 3, 3) or (3, 3),
        poses (B, T, 3) = x, y, yaw, instruction tokens (B, L) with lengths (B,). `initial_semantic_map_w`
        (B, C_f, n, n) continues episodes (None starts them); `generator` draws the pose noise, if configured."""
        B, T = images.shape[:2]
        poses, T_world_camera = self.perturb(poses, T_world_camera, generator)
        K = K.expand(B, 3, 3).repeat_interleave(T, dim=0)  # (B*T, 3, 3)
        features_c, projected_w, coverage_w = self._perceive_frames(
            images.reshape(B * T, *images.shape[2:]), T_world_camera.reshape(B * T, 4, 4), K)

        def unflat(x: torch.Tensor) -> torch.Tensor:
            return x.reshape(B, T, *x.shape[1:])

        projected_w, coverage_w = unflat(projected_w), unflat(coverage_w)
        semantic_map_w = accumulate(projected_w, coverage_w, self.leaky_lambda, initial_semantic_map_w)
        g = self.ground(semantic_map_w, poses, tokens=tokens, lengths=lengths)
        return GSMNOutputs(g.sentence_embedding, poses, unflat(features_c), projected_w, coverage_w, semantic_map_w,
                           g.relevance_map_w, g.relevance_map_r, g.goal_map_r, g.goal_map_w, g.v, g.omega,
                           g.stop_logit)

    # -- the policy's step interface -------------------------------------------------------------------------
    def step(self, image: torch.Tensor, T_world_camera: torch.Tensor, K: torch.Tensor, poses: torch.Tensor,
             sentence_embedding: torch.Tensor, state: torch.Tensor | None, generator: torch.Generator | None = None,
             kernels: InstructionKernels | None = None, substitute: Substitute | None = None
             ) -> tuple[GSMNOutputs, torch.Tensor]:
        """One step for B drones: image (B, H, W, 3), T_world_camera (B, 4, 4), K, poses (B, 3), sentence
        embeddings (B, E) (and optionally their `instruction_kernels`), and the carried state (the semantic map,
        None at the first step). Returns the step's outputs as a GSMNOutputs with T = 1, and the new state.
        `substitute`: a map intervention (see `ground`), which may also replace the semantic map, "semantic_map_w"
        (the new state is then the substitute, which later steps keep integrating)."""
        poses, T_world_camera = self.perturb(poses, T_world_camera, generator)
        p = self.perceive(image, T_world_camera, K, state)
        if substitute is not None:
            p = dataclasses.replace(p, semantic_map_w=substitute("semantic_map_w", p.semantic_map_w))
        g = self.ground(p.semantic_map_w, poses, sentence_embedding, kernels=kernels, substitute=substitute)

        def seq(x: torch.Tensor) -> torch.Tensor:
            return x.unsqueeze(1)

        outputs = GSMNOutputs(sentence_embedding, seq(poses), seq(p.features_c), seq(p.projected_features_w),
                              seq(p.coverage_w), seq(p.semantic_map_w), seq(g.relevance_map_w),
                              seq(g.relevance_map_r), seq(g.goal_map_r), seq(g.goal_map_w), seq(g.v), seq(g.omega),
                              seq(g.stop_logit))
        return outputs, p.semantic_map_w
