"""Training on a GPU (`--train.device cuda`): refused clearly where there is none; a run may move between devices
when it resumes; and, where a CUDA device exists, a run trained there saves checkpoints a CPU-only machine reads,
whose network computes what it computed there."""

from __future__ import annotations

import json

import pytest
import torch

from gsmn.config import ConfigError, preset, with_overrides
from gsmn.model.checkpoint import load_checkpoint, read_optimizer_state
from gsmn.training.dagger import train_dagger
from gsmn.training.run import RunFolder
from gsmn.training.supervised import train_supervised, validate

pytestmark = pytest.mark.training

FLAGS = {"task.horizon": "20", "train.epochs": "2", "train.batch_size": "2", "train.save_every_seconds": "0"}
CONFIG = with_overrides(preset("tiny"), FLAGS)
CUDA = torch.cuda.is_available()


def test_the_device_setting_is_checked():
    for bad in ("gpu", "cuda:", "cuda:x", "mps"):
        with pytest.raises(ConfigError, match="train.device"):
            with_overrides(CONFIG, {"train.device": bad})
    assert with_overrides(CONFIG, {"train.device": "cuda:1"}).train.device == "cuda:1"


@pytest.mark.skipif(CUDA, reason="this machine has a CUDA device")
def test_a_run_on_a_missing_gpu_is_refused_by_name_and_saves_nothing(stores, tmp_path):
    train, dev = stores
    with pytest.raises(ValueError, match="--train.device cuda: torch .* sees no CUDA device"):
        train_supervised(tmp_path / "run", "gsmn", with_overrides(CONFIG, {"train.device": "cuda"}), train, dev)
    assert not RunFolder(tmp_path / "run").has_state()


def test_a_run_may_change_its_device_and_threads_when_it_resumes(tmp_path):
    """The device, the thread counts and the save interval decide where and how fast the next batches are computed,
    not what was saved (which is always on the CPU)."""
    run = RunFolder(tmp_path / "run")
    run.start(CONFIG)
    run.start(with_overrides(CONFIG, {"train.device": "cuda"}))
    assert json.loads((tmp_path / "run" / "config.json").read_text())["train"]["device"] == "cuda"
    run.start(with_overrides(CONFIG, {"train.device": "cuda", "train.threads": "1"}))
    run.start(with_overrides(CONFIG, {"train.device": "cuda", "train.prefetch": "4", "train.save_every_seconds": "20"}))
    run.start(with_overrides(CONFIG, {"train.device": "cuda", "train.epochs": "3"}))


@pytest.mark.skipif(not CUDA, reason="needs a CUDA device")
def test_a_run_trained_on_the_gpu_is_read_on_the_cpu_and_computes_the_same(stores, tmp_path):
    train, dev = stores
    on_gpu = with_overrides(CONFIG, {"train.device": "cuda", "train.prefetch": "2"})  # read ahead, as the scripts do
    checkpoint = train_supervised(tmp_path / "gpu", "gsmn", on_gpu, train, dev, log=lambda s: None)
    log = RunFolder(tmp_path / "gpu").read_log()
    assert [r["epoch"] for r in log] == [1, 2] and log[-1]["train"]["loss"] < log[0]["train"]["loss"]
    # Every saved tensor is on the CPU: a machine without CUDA loads them without a map_location.
    for path in (checkpoint / "optimizer.safetensors", tmp_path / "gpu" / "state" / "optimizer.safetensors"):
        state = read_optimizer_state(path)["state"]
        assert state and all(t.device.type == "cpu" for s in state.values() for t in s.values()), path
    cpu_model, config, vocabulary, _ = load_checkpoint(checkpoint)
    gpu_model, _, _, _ = load_checkpoint(checkpoint, device="cuda")
    assert next(cpu_model.parameters()).device.type == "cpu"
    on_cpu, on_cuda = (validate(m, dev, vocabulary, config, 2) for m in (cpu_model, gpu_model))
    for name in ("loss_action", "loss_perception", "loss_grounding"):
        assert on_cuda[name] == pytest.approx(on_cpu[name], rel=2e-2, abs=1e-4), name
    # The run goes on, on the CPU, from the state it saved on the GPU.
    longer = with_overrides(CONFIG, {"train.epochs": "3"})
    train_supervised(tmp_path / "gpu", "gsmn", longer, train, dev, log=lambda s: None)
    assert [r["epoch"] for r in RunFolder(tmp_path / "gpu").read_log()] == [1, 2, 3]


@pytest.mark.skipif(not CUDA, reason="needs a CUDA device")
def test_dagger_trains_on_the_gpu_while_its_rollouts_fly_on_the_cpu(stores, tmp_path):
    """The policy the rollout workers load (run/policy, written from the GPU model) is read on the CPU."""
    train, dev = stores
    dagger = with_overrides(CONFIG, {"train.epochs": "1", "dagger.iterations": "2",  # rollouts before M: checked
                                     "dagger.rollouts_per_iteration": "2", "dagger.dataset_size": "3",
                                     "dagger.beta0": "0.5", "dagger.workers": "1"})
    start = train_supervised(tmp_path / "sup", "gsmn", dagger, train, log=lambda s: None)  # on the CPU
    checkpoint = train_dagger(tmp_path / "dagger", start, with_overrides(dagger, {"train.device": "cuda"}), train,
                              dev, log=lambda s: None)
    log = RunFolder(tmp_path / "dagger").read_log()
    assert [r["iteration"] for r in log] == [1, 2] and log[1]["learner_step_fraction"] > 0
    model, config, _, _ = load_checkpoint(checkpoint)
    assert config.train.device == "cuda" and next(model.parameters()).device.type == "cpu"
