"""The training objective (paper: Learning, Equation 1 and Auxiliary Objectives):

    J = w_act J_act + w_percept J_percept + w_lang J_lang + w_ground J_ground + w_plan J_plan

- J_act: 1/3 MSE(v) + 1/3 MSE(omega) + 1/3 BCE(stop), in normalised units, averaged over the real steps.
- J_percept: cross-entropy of the perception head on the semantic map (GSMN) or image features (FPV) at the
  landmarks visible in the current image; averaged over those landmarks at each step, then over every step
  that has at least one (the original stopped at the first step without one: not copied).
- J_lang: cross-entropy of the named landmark's class plus cross-entropy of the side, from the sentence
  embedding. Several models share a noun phrase ("palm tree" x4), so the landmark accuracy cannot reach 1.
- J_ground: binary (2-way softmax) classification of the relevance map at the same landmark cells as
  J_percept: is this the landmark the instruction names; averaged like J_percept.
- J_plan: binary classification of the world-frame goal map: the goal cell is positive and one other cell,
  drawn uniformly at every step, negative; averaged over the real steps (GSMN only).

A switched-off objective (LossConfig's ablation switches, and J_plan for kinds without it) is not computed and
contributes exactly zero. `compute_losses` also returns the accuracies the paper plots.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from gsmn.config import LossConfig
from gsmn.model.batch import Batch
from gsmn.model.fpv import FPVOutputs
from gsmn.model.gsmn import GSMNOutputs
from gsmn.model.labels import Labels, make_labels

TERMS = ("action", "perception", "language", "grounding", "goal")
ACCURACIES = ("perception", "grounding", "goal", "instruction_landmark", "instruction_side", "stop")
KINDS_WITH_PLAN = ("gsmn",)


@dataclass(frozen=True)
class LossOutputs:
    total: torch.Tensor  # scalar, the weighted sum of the switched-on terms
    terms: dict[str, torch.Tensor]  # unweighted value of each objective in TERMS (0 when switched off)
    accuracies: dict[str, float]  # each of ACCURACIES; NaN when off or not measurable in this batch


def objectives_for(kind: str, config: LossConfig) -> LossConfig:
    """The loss config a model kind trains with: J_plan off for "gsmn-no-plan" and the FPV baselines."""
    return config if kind in KINDS_WITH_PLAN else dataclasses.replace(config, goal=False)


def gather_cells(maps: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """Values of maps (B, T, C, H, W) at cells (B, M, 2) or (B, T, M, 2) of (row, col) -> (B, T, M, C)."""
    B, T, C, H, W = maps.shape
    index = cells[..., 0] * W + cells[..., 1]  # (B, M) or (B, T, M)
    if index.dim() == 2:
        index = index[:, None].expand(B, T, index.shape[-1])
    flat = maps.flatten(3)  # (B, T, C, H*W)
    values = flat.gather(3, index[:, :, None, :].expand(B, T, C, index.shape[-1]))  # (B, T, C, M)
    return values.transpose(2, 3)


def _per_step_mean(loss: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """Mean over visible entries (B, T, M) at each step, then over the steps that have any."""
    v = visible.float()
    count = v.sum(-1)  # (B, T)
    per_step = (loss * v).sum(-1) / count.clamp(min=1)
    has = count > 0
    return per_step[has].mean() if bool(has.any()) else loss.sum() * 0.0


def _accuracy(logits: torch.Tensor, labels: torch.Tensor, where: torch.Tensor | None = None) -> float:
    correct = logits.argmax(-1) == labels
    if where is not None:
        correct = correct[where]
    return float(correct.float().mean()) if correct.numel() else math.nan


def action_loss(outputs: GSMNOutputs | FPVOutputs, batch: Batch) -> tuple[torch.Tensor, float]:
    """J_act and the STOP accuracy over the real steps."""
    mask = batch.mask.float()
    target = batch.actions  # (B, T, 3)
    per_step = ((outputs.v - target[..., 0]).square() + (outputs.omega - target[..., 1]).square()
                + F.binary_cross_entropy_with_logits(outputs.stop_logit, target[..., 2], reduction="none")) / 3
    loss = (per_step * mask).sum() / mask.sum().clamp(min=1)
    stop_correct = ((outputs.stop_logit > 0) == (target[..., 2] > 0.5))[batch.mask]
    return loss, float(stop_correct.float().mean()) if stop_correct.numel() else math.nan


def compute_losses(model: torch.nn.Module, batch: Batch, outputs: GSMNOutputs | FPVOutputs, config: LossConfig,
                   labels: Labels | None = None, generator: torch.Generator | None = None) -> LossOutputs:
    """Every objective of `model` (a GSMN or GSFPV with its `heads`) on `outputs = model(batch ...)`."""
    config = objectives_for(model.kind, config)
    heads = model.heads
    is_map = isinstance(outputs, GSMNOutputs)
    if labels is None:
        labels = make_labels(batch, model.geometry, model.image_size)
    zero = outputs.v.new_zeros(())
    terms = dict.fromkeys(TERMS, zero)
    acc = dict.fromkeys(ACCURACIES, math.nan)

    terms["action"], acc["stop"] = action_loss(outputs, batch)
    visible = labels.visible
    classes = batch.landmark_class[:, None, :].expand_as(visible)  # (B, T, M)
    if config.perception:
        cells = labels.landmark_cell_w if is_map else labels.landmark_cell_c
        features = outputs.semantic_map_w if is_map else outputs.features_c
        logits = heads.perception(gather_cells(features, cells))  # (B, T, M, classes)
        ce = F.cross_entropy(logits.flatten(0, 2), classes.flatten(), reduction="none").view_as(classes)
        terms["perception"] = _per_step_mean(ce, visible)
        acc["perception"] = _accuracy(logits.detach(), classes, visible)
    if config.grounding:
        cells = labels.landmark_cell_w if is_map else labels.landmark_cell_c
        relevance = outputs.relevance_map_w if is_map else outputs.relevance_map_c
        logits = heads.grounding(gather_cells(relevance, cells))  # (B, T, M, 2)
        named = labels.is_named[:, None, :].expand_as(visible).long()
        ce = F.cross_entropy(logits.flatten(0, 2), named.flatten(), reduction="none").view_as(named)
        terms["grounding"] = _per_step_mean(ce, visible)
        acc["grounding"] = _accuracy(logits.detach(), named, visible)
    if config.language:
        e = outputs.sentence_embedding
        landmark_logits, side_logits = heads.language_landmark(e), heads.language_side(e)
        terms["language"] = F.cross_entropy(landmark_logits, batch.named_class) + F.cross_entropy(side_logits,
                                                                                                   batch.side)
        acc["instruction_landmark"] = _accuracy(landmark_logits.detach(), batch.named_class)
        acc["instruction_side"] = _accuracy(side_logits.detach(), batch.side)
    if config.goal:
        if not is_map or heads.goal is None:
            raise ValueError(f"J_plan needs a model with a world-frame goal map, not {model.kind!r}")
        terms["goal"], acc["goal"] = goal_loss(outputs.goal_map_w, labels.goal_cell_w, batch.mask, heads.goal,
                                               generator)

    weights = {"action": config.action_weight, "perception": config.perception_weight,
               "language": config.language_weight, "grounding": config.grounding_weight, "goal": config.goal_weight}
    switched_on = {"action": True, "perception": config.perception, "language": config.language,
                   "grounding": config.grounding, "goal": config.goal}
    total = sum((weights[k] * terms[k] for k in TERMS if switched_on[k]), zero)
    return LossOutputs(total=total, terms=terms, accuracies=acc)


def goal_loss(goal_map_w: torch.Tensor, goal_cell_w: torch.Tensor, mask: torch.Tensor, head: torch.nn.Module,
              generator: torch.Generator | None = None) -> tuple[torch.Tensor, float]:
    """J_plan on goal maps (B, T, C_g, n, n): the goal cell (B, 2) positive, one random other cell negative."""
    B, T, _, H, W = goal_map_w.shape
    positive = (goal_cell_w[:, 0] * W + goal_cell_w[:, 1])[:, None].expand(B, T)  # (B, T)
    negative = torch.randint(0, H * W - 1, (B, T), generator=generator, device=goal_map_w.device)
    negative = negative + (negative >= positive).long()  # uniform over the other cells
    cells = torch.stack([positive, negative], dim=-1)  # (B, T, 2 examples)
    cells_rc = torch.stack([cells // W, cells % W], dim=-1)  # (B, T, 2, 2)
    logits = head(gather_cells(goal_map_w, cells_rc))  # (B, T, 2 examples, 2 classes)
    labels = torch.tensor([1, 0], device=logits.device).expand(B, T, 2)
    ce = F.cross_entropy(logits.flatten(0, 2), labels.flatten(), reduction="none").view(B, T, 2)
    m = mask.float()
    loss = (ce.mean(-1) * m).sum() / m.sum().clamp(min=1)
    return loss, _accuracy(logits.detach(), labels, mask[..., None].expand(B, T, 2))

