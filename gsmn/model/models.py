"""Building a model by kind (paper: Systems; Table 1 and Table 2 rows).

- "gsmn": GSMN trained with every objective.
- "gsmn-no-plan": the same network trained without J_plan (the paper's GSMN - J_plan row, the fair comparison
  for the baselines); only the loss differs (`gsmn.model.losses.objectives_for`).
- "gs-fpv", "gs-fpv-mem": the first-person baselines.
"""

from __future__ import annotations

import torch

from gsmn.config import RunConfig
from gsmn.model.batch import Batch
from gsmn.model.fpv import GSFPV, FPVOutputs
from gsmn.model.gsmn import GSMN, GSMNOutputs
from gsmn.model.vocabulary import Vocabulary

KINDS = ("gsmn", "gsmn-no-plan", "gs-fpv", "gs-fpv-mem")

Model = GSMN | GSFPV
Outputs = GSMNOutputs | FPVOutputs


def build_model(kind: str, config: RunConfig | None = None, vocabulary: Vocabulary | None = None) -> Model:
    """A freshly initialised model of `kind` for `config` (default: the paper preset) and `vocabulary`
    (default: `Vocabulary.default()`)."""
    config = config or RunConfig()
    size = len(vocabulary or Vocabulary.default())
    if kind in ("gsmn", "gsmn-no-plan"):
        return GSMN(config, size, kind)
    if kind in ("gs-fpv", "gs-fpv-mem"):
        return GSFPV(config, size, memory=kind == "gs-fpv-mem", kind=kind)
    raise ValueError(f"unknown model kind {kind!r}; choose from {', '.join(KINDS)}")


def forward_batch(model: Model, batch: Batch, generator: torch.Generator | None = None) -> Outputs:
    """`model` on a whole batch of episodes."""
    return model(batch.images, batch.T_world_camera, batch.K, batch.poses, batch.tokens, batch.lengths,
                 generator=generator)
