"""The first-person baselines GS-FPV and GS-FPV-MEM (paper: Systems; original code for the sizes).

The same ResNet features and the same language-derived filters as GSMN, applied to the 18x32 image features
instead of a map: no projection, no semantic map, no frame change.

    relevance_map_c = LeakyReLU(1x1 language filter * features_c)        (B, T, 3, 18, 32)
    goal_map_c      = language 3x3 filters (relevance_map_c)              (B, T, 2, 18, 32)
    x               = [dropout(flatten([R_c, G_c])) (2880); sentence embedding (30) (; LSTM output (32))]
    out             = W2 [x; LeakyReLU(W1 x)]   (hidden 32)

GS-FPV-MEM stores the flattened [R_c, G_c] in an LSTM(2880 -> 32) whose state runs across the episode's steps
and feeds its output to the perceptron. The baselines get the same auxiliary objectives as GSMN except the
planning objective (the goal may be out of view): perception and grounding at landmark cells of the image
feature map.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
import torch.nn as nn

from gsmn.config import RunConfig
from gsmn.model.controller import DensePerceptron, split_actions
from gsmn.model.filters import InstructionKernels
from gsmn.model.grid import MapGeometry
from gsmn.model.gsmn import add_shared_modules
from gsmn.model.heads import AuxiliaryHeads
from gsmn.model.perception import DOWNSCALE, standardise

MemoryState = tuple[torch.Tensor, torch.Tensor] | None  # LSTM (h, c), each (1, B, hidden)


@dataclass(frozen=True)
class FPVOutputs:
    """Everything a first-person baseline computes for B episodes of T steps."""

    sentence_embedding: torch.Tensor  # (B, E)
    poses: torch.Tensor  # (B, T, 3) unused by the network; kept for viewers
    features_c: torch.Tensor  # (B, T, C_f, h, w)
    relevance_map_c: torch.Tensor  # (B, T, 3, h, w)
    goal_map_c: torch.Tensor  # (B, T, 2, h, w)
    memory: torch.Tensor | None  # (B, T, hidden) LSTM outputs (GS-FPV-MEM only)
    v: torch.Tensor  # (B, T)
    omega: torch.Tensor  # (B, T)
    stop_logit: torch.Tensor  # (B, T)

    def maps(self) -> dict[str, torch.Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name.endswith("_c")}


class GSFPV(nn.Module):
    """GS-FPV (memory=False) or GS-FPV-MEM (memory=True)."""

    def __init__(self, config: RunConfig, vocabulary_size: int, memory: bool, kind: str | None = None):
        super().__init__()
        m = config.model
        self.kind = kind or ("gs-fpv-mem" if memory else "gs-fpv")
        self.config = config
        self.geometry = MapGeometry(config.world.field_size, m.map_size, m.robot_map_size)  # for the labels only
        self.image_size = (config.camera.width, config.camera.height)
        slope = m.leaky_relu_slope
        add_shared_modules(self, m, vocabulary_size)
        h, w = config.camera.height // DOWNSCALE, config.camera.width // DOWNSCALE
        map_features = (m.relevance_channels + m.goal_channels) * h * w  # 5 * 18 * 32 = 2880
        self.memory = nn.LSTM(map_features, m.fpv_memory, batch_first=True) if memory else None
        extra = m.instruction_hidden + (m.fpv_memory if memory else 0)
        self.perceptron = DensePerceptron(map_features, extra, m.fpv_hidden, m.controller_dropout, slope)
        self.heads = AuxiliaryHeads(m.feature_channels, m.relevance_channels, None, m.instruction_hidden,
                                    m.landmark_classes, m.side_classes)

    def memory_columns(self) -> slice:
        """The perceptron's input columns that read the LSTM's outputs, after the maps and the sentence embedding
        (the same in its hidden and output layers; GS-FPV-MEM only)."""
        n_memory = self.config.model.fpv_memory
        n_in = self.perceptron.hidden.in_features - n_memory
        return slice(n_in, n_in + n_memory)

    def encode_instruction(self, tokens: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        return self.encoder(tokens, lengths)

    def instruction_kernels(self, sentence_embedding: torch.Tensor) -> InstructionKernels:
        """The relevance and goal filters' kernels for sentence embeddings (B, E)."""
        return InstructionKernels.of(self.relevance_filter, self.goal_filter, sentence_embedding)

    def _run(self, images: torch.Tensor, poses: torch.Tensor, sentence_embedding: torch.Tensor, state: MemoryState,
             kernels: InstructionKernels | None = None) -> tuple[FPVOutputs, MemoryState]:
        B, T = images.shape[:2]
        if kernels is None:
            kernels = self.instruction_kernels(sentence_embedding)
        features_c = self.resnet(standardise(images.reshape(B * T, *images.shape[2:])))  # (B*T, C_f, h, w)
        features_c = features_c.reshape(B, T, *features_c.shape[1:])
        relevance_c = self.relevance_filter(features_c, kernels.relevance)  # (B, T, 3, h, w)
        goal_c = self.goal_filter(relevance_c, kernels.goal)  # (B, T, 2, h, w)
        x = torch.cat([relevance_c, goal_c], dim=2).flatten(2)  # (B, T, 2880)
        extra = sentence_embedding[:, None].expand(B, T, sentence_embedding.shape[-1])
        memory = None
        if self.memory is not None:
            memory, state = self.memory(x, state)  # (B, T, hidden)
            extra = torch.cat([extra, memory], dim=-1)
        v, omega, stop_logit = split_actions(self.perceptron(x, extra))  # each (B, T)
        return FPVOutputs(sentence_embedding, poses, features_c, relevance_c, goal_c, memory, v, omega,
                          stop_logit), state

    def forward(self, images: torch.Tensor, T_world_camera: torch.Tensor, K: torch.Tensor, poses: torch.Tensor,
                tokens: torch.Tensor, lengths: torch.Tensor, initial_state: MemoryState = None,
                generator: torch.Generator | None = None) -> FPVOutputs:
        """Same inputs as GSMN.forward; the camera poses are not used (no projection)."""
        outputs, _ = self._run(images, poses, self.encode_instruction(tokens, lengths), initial_state)
        return outputs

    def step(self, image: torch.Tensor, T_world_camera: torch.Tensor, K: torch.Tensor, poses: torch.Tensor,
             sentence_embedding: torch.Tensor, state: MemoryState, generator: torch.Generator | None = None,
             kernels: InstructionKernels | None = None) -> tuple[FPVOutputs, MemoryState]:
        """One step for B drones (see GSMN.step); the state is the LSTM's (h, c), None at the first step."""
        return self._run(image[:, None], poses[:, None], sentence_embedding, state, kernels)


def memory_from_fpv(fpv: GSFPV, seed: int = 0) -> GSFPV:
    """A GS-FPV-MEM that computes exactly the actions of a trained GS-FPV (a warm start; not in the paper).

    Every weight the two share is copied; the LSTM keeps a fresh initialisation (seeded); the perceptron's weights
    on the LSTM's outputs are zero, so the memory has no say until training gives it one. The perceptron's input
    is [maps; sentence] in GS-FPV and [maps; sentence; memory] in GS-FPV-MEM, its output layer's
    [inputs; hidden] likewise (docs/training.md, "`checkpoints/gs-fpv-mem`").
    """
    if getattr(fpv, "kind", None) != "gs-fpv":
        raise ValueError(f"memory_from_fpv needs a GS-FPV; this is a {getattr(fpv, 'kind', type(fpv).__name__)!r}")
    with torch.random.fork_rng(devices=[]):  # seeds the LSTM's initialisation without touching the caller's RNG
        torch.manual_seed(seed)
        mem = GSFPV(fpv.config, fpv.encoder.embedding.num_embeddings, memory=True)
    mem = mem.to(next(fpv.parameters()).device)
    source, columns = fpv.state_dict(), mem.memory_columns()
    state = {}
    for name, tensor in mem.state_dict().items():
        if name.startswith("memory."):
            state[name] = tensor
        elif name in ("perceptron.hidden.weight", "perceptron.out.weight"):
            w = torch.zeros_like(tensor)
            w[:, :columns.start] = source[name][:, :columns.start]
            w[:, columns.stop:] = source[name][:, columns.start:]  # the output layer's hidden units; none for `hidden`
            state[name] = w
        else:
            state[name] = source[name]
    mem.load_state_dict(state, strict=True)
    return mem.train(fpv.training)


def freeze_all_but_memory(model: GSFPV) -> tuple[list[nn.Parameter], list[nn.Parameter]]:
    """Freeze a GS-FPV-MEM except its memory's path (`train.trainable memory`; not in the paper): the LSTM and the
    perceptron's weights on the LSTM's outputs (the memory's columns of its hidden and output layers). Returns
    (the LSTM's parameters, the two perceptron weights). The perceptron's weights keep requires_grad, but a hook
    zeroes their gradients outside the memory's columns; give them no weight decay, so that Adam leaves those
    entries exactly as they are (a zero gradient and zero moments give a zero step)."""
    if getattr(model, "memory", None) is None:
        raise ValueError(f"train.trainable memory needs a GS-FPV-MEM; this is a {getattr(model, 'kind', '?')!r}")
    for p in model.parameters():
        p.requires_grad_(False)
    lstm = list(model.memory.parameters())
    for p in lstm:
        p.requires_grad_(True)
    columns = model.memory_columns()
    masked = [model.perceptron.hidden.weight, model.perceptron.out.weight]
    for weight in masked:
        mask = torch.zeros_like(weight)
        mask[:, columns] = 1.0
        weight.requires_grad_(True)
        weight.register_hook(lambda grad, mask=mask: grad * mask)
    return lstm, masked
