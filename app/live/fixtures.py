"""An untrained GSMN checkpoint for the dashboard's tests, benchmark and demos while no trained one exists.

Its weights are the seeded initial ones, so its maps are the untrained network's (structured by the projection
and the leaky integrator, meaningless as landmarks). With `flying=True` the controller's output biases are
shifted so that it flies forward and rarely says STOP: an untrained GSMN otherwise stops at its first step
(P(stop) about 0.6), which leaves nothing to watch or time.
"""

from __future__ import annotations

from pathlib import Path

import torch


def make_untrained_checkpoint(folder: str | Path, preset_name: str = "tiny", flying: bool = True,
                              seed: int = 0) -> Path:
    from gsmn.config import preset
    from gsmn.model import build_model, save_checkpoint
    from gsmn.model.vocabulary import Vocabulary

    torch.manual_seed(seed)
    config = preset(preset_name)
    vocabulary = Vocabulary.default()
    model = build_model("gsmn", config, vocabulary)
    if flying:
        with torch.no_grad():
            out = model.controller.perceptron.out  # raw (v, omega, stop_logit)
            out.bias[0] += 1.5  # v = sigmoid(.) ~ 0.8 of the top speed
            out.bias[2] -= 6.0  # P(stop) well under 0.5
    return save_checkpoint(folder, model, config, vocabulary,
                           {"note": "untrained" + (", controller biased to fly" if flying else ""), "seed": seed})
