"""GSMN and its baselines (paper: Model Architecture, Auxiliary Objectives, Systems). See docs/model.md."""

from gsmn.model.batch import Batch, EpisodeSample, collate
from gsmn.model.checkpoint import CheckpointError, load_checkpoint, load_policy, read_checkpoint_kind, save_checkpoint
from gsmn.model.fpv import GSFPV, FPVOutputs
from gsmn.model.gsmn import GSMN, GroundingOutputs, GSMNOutputs, PerceptionOutputs
from gsmn.model.losses import LossOutputs, compute_losses, objectives_for
from gsmn.model.models import KINDS, build_model, forward_batch
from gsmn.model.policy import GSMNPolicy, ModelPolicy
from gsmn.model.vocabulary import Vocabulary

__all__ = [
    "KINDS", "Batch", "CheckpointError", "EpisodeSample", "FPVOutputs", "GSFPV", "GSMN", "GSMNOutputs",
    "GSMNPolicy", "GroundingOutputs", "LossOutputs", "ModelPolicy", "PerceptionOutputs", "Vocabulary",
    "build_model", "collate", "compute_losses", "forward_batch", "load_checkpoint", "load_policy",
    "objectives_for", "read_checkpoint_kind", "save_checkpoint",
]
