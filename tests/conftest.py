"""Shared test set-up: headless rendering must be chosen before any test module imports mujoco."""

import os

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """Expert stores for the training tests: 4 train episodes (environments 0-3) and 2 dev (85, 86) of the tiny
    preset, each the first 20 steps of the expert's flight, so that those tests take seconds."""
    from gsmn.config import preset, with_overrides
    from gsmn.training.collect import collect_expert
    from gsmn.training.store import EpisodeStore

    config = with_overrides(preset("tiny"), {"task.horizon": "20"})
    root = tmp_path_factory.mktemp("data")
    train, dev = EpisodeStore(root / "train"), EpisodeStore(root / "dev")
    collect_expert(train, [0, 1, 2, 3], config, workers=2)
    collect_expert(dev, [85, 86], config)
    return train, dev
