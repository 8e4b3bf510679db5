"""Supervised training: the tiny preset trains end to end, and a run killed at any point resumes exactly."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from gsmn.config import preset, with_overrides
from gsmn.model.checkpoint import CheckpointError, load_checkpoint, read_optimizer_state
from gsmn.training.dagger import train_dagger
from gsmn.training.run import RunError, RunFolder, TrainState, read_progress
from gsmn.training.store import EpisodeStore, StoreError
from gsmn.training.supervised import make_model_and_optimizer, train_supervised

pytestmark = pytest.mark.training

# Short episodes (the first 20 steps of the expert's flight, conftest.py's `stores`) keep these tests to seconds.
FLAGS = {"task.horizon": "20", "train.epochs": "3", "train.batch_size": "2", "train.save_every_seconds": "0"}
CONFIG = with_overrides(preset("tiny"), FLAGS)


def test_tiny_preset_trains_end_to_end_and_its_loss_falls(stores, tmp_path):
    train, dev = stores
    lines, reports = [], []
    checkpoint = train_supervised(tmp_path / "run", "gsmn", CONFIG, train, dev, log=lines.append,
                                  on_progress=reports.append)
    # One progress report per batch (4 episodes in batches of 2), the last of each epoch complete.
    assert [(r["epoch"], r["batch"], r["batches"]) for r in reports] == [(e, b, 2) for e in (1, 2, 3) for b in (1, 2)]
    assert RunFolder(tmp_path / "run").read_progress()["phase"] == "done"
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in log] == [1, 2, 3] and len(lines) == 3
    assert log[-1]["train"]["loss"] < log[0]["train"]["loss"]
    assert log[-1]["dev"]["loss_action"] < log[0]["dev"]["loss_action"]
    for name in ("acc_perception", "acc_grounding", "acc_goal", "acc_instruction_landmark", "acc_instruction_side"):
        assert 0.0 <= log[-1]["dev"][name] <= 1.0, name
    model, config, _, meta = load_checkpoint(checkpoint)
    assert model.kind == "gsmn" and config == CONFIG and meta["metrics"]["epoch"] == 3
    # Training again in the same folder resumes a finished run: nothing more to do, nothing lost.
    train_supervised(tmp_path / "run", "gsmn", CONFIG, train, dev, log=lines.append)
    assert len(lines) == 3
    for change in ({"train.learning_rate": "0.01"}, {"train.epochs": "2"}, {"train.epochs": "4", "train.seed": "1"}):
        with pytest.raises(RunError, match="different configuration"):
            train_supervised(tmp_path / "run", "gsmn", with_overrides(CONFIG, change), train, dev)


def test_a_finished_run_extended_by_an_epoch_matches_a_run_of_that_length(stores, tmp_path):
    train, dev = stores
    longer = with_overrides(CONFIG, {"train.epochs": "4"})
    train_supervised(tmp_path / "extended", "gsmn", CONFIG, train, dev)
    train_supervised(tmp_path / "extended", "gsmn", longer, train, dev)  # more epochs: the run goes on
    train_supervised(tmp_path / "straight", "gsmn", longer, train, dev)
    logs = {name: RunFolder(tmp_path / name).read_log() for name in ("extended", "straight")}
    assert [r["epoch"] for r in logs["extended"]] == [1, 2, 3, 4]
    assert logs["extended"][-1]["train"]["loss"] == pytest.approx(logs["straight"][-1]["train"]["loss"])
    extended = load_file(tmp_path / "extended" / "state" / "weights.safetensors")
    straight = load_file(tmp_path / "straight" / "state" / "weights.safetensors")
    for key, value in straight.items():
        torch.testing.assert_close(extended[key], value, msg=key)
    assert json.loads((tmp_path / "extended" / "config.json").read_text())["train"]["epochs"] == 4


def test_a_run_from_a_checkpoint_keeps_the_checkpoints_architecture(stores, tmp_path):
    """--init of a checkpoint with the original's sigmoid kernels under a config that says signed: the run trains
    and records the checkpoint's model settings (no weight shape would have caught the difference)."""
    train, _ = stores
    one = with_overrides(CONFIG, {"train.epochs": "1"})
    sigmoid = with_overrides(one, {"model.filter_activation": "sigmoid"})
    start = train_supervised(tmp_path / "sigmoid", "gsmn", sigmoid, train, log=lambda s: None)
    assert one.model.filter_activation == "none"
    end = train_supervised(tmp_path / "continued", "gsmn", one, train, init=start, log=lambda s: None)
    model, config, _, _ = load_checkpoint(end)
    assert config.model == sigmoid.model and model.goal_filter.activation == "sigmoid"
    assert json.loads((tmp_path / "continued" / "config.json").read_text())["model"]["filter_activation"] == "sigmoid"


def test_a_run_from_a_checkpoint_can_go_on_with_its_optimizer_state(stores, tmp_path):
    """A run's checkpoint holds its Adam state; --init-optimizer starts the next run's Adam from it (moments and
    step counts) at the next run's learning rate. Without the flag Adam starts fresh; a checkpoint saved without
    optimizer state is refused by name."""
    train, _ = stores
    one = with_overrides(CONFIG, {"train.epochs": "1"})
    start = train_supervised(tmp_path / "first", "gsmn", one, train, log=lambda s: None)
    assert not list(start.glob("*.pt")) and not list((tmp_path / "first" / "state").glob("*.pt"))  # no pickle
    saved = read_optimizer_state(start / "optimizer.safetensors")
    in_run = read_optimizer_state(tmp_path / "first" / "state" / "optimizer.safetensors")
    assert saved["state"] and saved["state"].keys() == in_run["state"].keys()
    slower = with_overrides(one, {"train.learning_rate": "0.0001"})
    _, _, optimizer = make_model_and_optimizer("gsmn", slower, start, init_optimizer=True)
    state = optimizer.state_dict()
    assert {g["lr"] for g in state["param_groups"]} == {0.0001}
    for key, value in saved["state"].items():
        assert float(state["state"][key]["step"]) == float(value["step"]) == 2.0  # 4 episodes, batches of 2
        torch.testing.assert_close(state["state"][key]["exp_avg_sq"], value["exp_avg_sq"])
    assert not make_model_and_optimizer("gsmn", slower, start)[2].state_dict()["state"]
    end = train_supervised(tmp_path / "continued", "gsmn", slower, train, init=start, init_optimizer=True,
                           log=lambda s: None)
    after = read_optimizer_state(end / "optimizer.safetensors")
    assert {float(v["step"]) for v in after["state"].values()} == {4.0}  # it went on counting
    saved_bytes = (start / "optimizer.safetensors").read_bytes()
    (start / "optimizer.safetensors").write_bytes(saved_bytes[:100] + b"\xff" * 64 + saved_bytes[164:])  # damaged
    with pytest.raises(CheckpointError, match="optimizer.safetensors is unreadable"):
        train_supervised(tmp_path / "damaged", "gsmn", slower, train, init=start, init_optimizer=True)
    (start / "optimizer.safetensors").unlink()
    with pytest.raises(CheckpointError, match="holds no optimizer state"):
        train_supervised(tmp_path / "refused", "gsmn", slower, train, init=start, init_optimizer=True)
    # A run that already started resumes from its own state, Adam included, whatever became of `init` since.
    longer = with_overrides(slower, {"train.epochs": "2"})
    end = train_supervised(tmp_path / "continued", "gsmn", longer, train, init=start, init_optimizer=True,
                           log=lambda s: None)
    after = read_optimizer_state(end / "optimizer.safetensors")
    assert {float(v["step"]) for v in after["state"].values()} == {6.0}


def _cli(run: Path, data: Path) -> list[str]:
    args = [sys.executable, "-m", "gsmn.cli", "train", "supervised", "--data", str(data), "--run", str(run),
            "--preset", "tiny"]
    for key, value in FLAGS.items():
        args += ["--" + key.replace("_", "-"), value]
    return args


def test_a_killed_run_resumes_to_the_same_state_as_an_uninterrupted_one(stores, tmp_path):
    train, _ = stores
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    subprocess.run(_cli(whole, train.root), check=True, capture_output=True)
    # Kill the second run with SIGKILL once it has saved state in the middle of its second epoch.
    proc = subprocess.Popen(_cli(killed, train.root), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline:
            state = killed / "state" / "state.json"
            try:
                if state.is_file() and json.loads(state.read_text())["step"] >= 3:
                    break
            except (json.JSONDecodeError, KeyError):
                pass  # caught mid-rename; look again
            assert proc.poll() is None, "the run finished before it could be killed"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    subprocess.run(_cli(killed, train.root), check=True, capture_output=True)
    a = load_file(whole / "checkpoint" / "weights.safetensors")
    b = load_file(killed / "checkpoint" / "weights.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    log_a = (whole / "log.jsonl").read_text().splitlines()
    log_b = (killed / "log.jsonl").read_text().splitlines()
    assert [json.loads(x)["train"]["loss"] for x in log_a] == [json.loads(x)["train"]["loss"] for x in log_b]


def test_reading_ahead_on_threads_trains_the_same_weights_and_resumes_with_it_changed(stores, tmp_path):
    """train.prefetch reads (and mirrors) the next batches on threads while one trains: the same episodes in the same
    order, so the same weights to the bit; a run stopped mid-epoch may resume with another setting."""
    train, _ = stores
    mirrored = with_overrides(CONFIG, {"train.mirror": "0.5", "train.epochs": "2"})
    in_turn = train_supervised(tmp_path / "in_turn", "gsmn", mirrored, train, log=lambda s: None)
    ahead = with_overrides(mirrored, {"train.prefetch": "3"})
    stops = iter([True])  # stop at the first saved state inside an epoch, then run to the end
    train_supervised(tmp_path / "ahead", "gsmn", ahead, train, log=lambda s: None,
                     stop_after=lambda state: state.batch > 0 and next(stops, False))
    assert RunFolder(tmp_path / "ahead").read_progress()["phase"] == "train"
    resumed = train_supervised(tmp_path / "ahead", "gsmn", with_overrides(ahead, {"train.prefetch": "1"}), train,
                               log=lambda s: None)
    a, b = load_file(in_turn / "weights.safetensors"), load_file(resumed / "weights.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    losses = [[r["train"]["loss"] for r in RunFolder(tmp_path / name).read_log()] for name in ("in_turn", "ahead")]
    assert losses[0] == losses[1] and len(losses[0]) == 2


def test_an_episode_that_cannot_be_read_ahead_stops_training_by_its_name(stores, tmp_path):
    train, _ = stores
    broken = EpisodeStore(tmp_path / "broken")
    for key in train.keys():
        broken.path(key).write_bytes(train.path(key).read_bytes())
    broken.path(train.keys()[-1]).write_bytes(b"not an npz")
    config = with_overrides(CONFIG, {"train.prefetch": "2"})
    with pytest.raises(StoreError, match=train.keys()[-1]):
        train_supervised(tmp_path / "run", "gsmn", config, broken, log=lambda s: None)


def test_a_memory_only_run_trains_the_memory_and_leaves_every_other_weight_as_it_was(stores, tmp_path):
    """train.trainable memory: a GS-FPV-MEM's LSTM and the perceptron's columns on its outputs train; every other
    weight (the rest of the perceptron included, despite Adam's weight decay) stays bit for bit, also across a
    resumption; a model without a memory is refused."""
    train, _ = stores
    one = with_overrides(CONFIG, {"train.epochs": "1", "train.trainable": "memory"})
    initial = {k: v.clone() for k, v in make_model_and_optimizer("gs-fpv-mem", one, None)[0].state_dict().items()}
    train_supervised(tmp_path / "run", "gs-fpv-mem", one, train, log=lambda s: None)
    two = with_overrides(one, {"train.epochs": "2"})  # resumes the finished run: Adam's two groups reload
    final = load_file(train_supervised(tmp_path / "run", "gs-fpv-mem", two, train, log=lambda s: None)
                      / "weights.safetensors")
    n_memory = CONFIG.model.fpv_memory
    n_in = initial["perceptron.hidden.weight"].shape[1] - n_memory
    for name, before in initial.items():
        after = final[name]
        if name.startswith("memory."):
            assert not torch.equal(after, before), name
        elif name in ("perceptron.hidden.weight", "perceptron.out.weight"):
            columns = slice(n_in, n_in + n_memory)
            assert not torch.equal(after[:, columns], before[:, columns]), name
            assert torch.equal(after[:, :n_in], before[:, :n_in]) and torch.equal(after[:, n_in + n_memory:],
                                                                                   before[:, n_in + n_memory:]), name
        else:
            assert torch.equal(after, before), name
    with pytest.raises(ValueError, match="needs a GS-FPV-MEM"):
        make_model_and_optimizer("gs-fpv", one, None)


DAGGER = with_overrides(CONFIG, {"train.epochs": "1", "dagger.iterations": "2", "dagger.rollouts_per_iteration": "2",
                                 "dagger.dataset_size": "3", "dagger.beta0": "0.5", "dagger.workers": "1"})


@pytest.fixture(scope="module")
def supervised_checkpoint(stores, tmp_path_factory) -> Path:
    train, _ = stores
    return train_supervised(tmp_path_factory.mktemp("sup") / "run", "gsmn", DAGGER, train, log=lambda s: None)


def test_dagger_keeps_m_rollouts_and_mixes_in_the_policy_as_beta_falls(stores, supervised_checkpoint, tmp_path):
    train, dev = stores
    reports = []
    checkpoint = train_dagger(tmp_path / "dagger", supervised_checkpoint, DAGGER, train, dev, log=lambda s: None,
                              on_progress=reports.append)
    collected = [(r["iteration"], r["done"]) for r in reports if r["phase"] == "collect"]
    assert collected == [(1, 0), (1, 1), (1, 2), (2, 0), (2, 1), (2, 2)]
    assert {r["iteration"] for r in reports if r["phase"] == "train"} == {1, 2}
    assert reports[-1] == {"phase": "done", "iteration": 2, "iterations": 2}
    # what a monitor (the dashboard) reads of it: the iterations planned come from the run's config.json
    p = read_progress(tmp_path / "dagger")
    assert (p.phase, p.done, p.iterations, p.fraction, len(p.log)) == ("done", 2, 2, 1.0, 2)
    assert read_progress(tmp_path / "not-started") is None
    log = [json.loads(line) for line in (tmp_path / "dagger" / "log.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in log] == [1, 2]
    assert [r["beta"] for r in log] == [0.5, 0.25]
    assert all(r["dataset"] == 3 for r in log), "the dataset stays at M rollouts"
    assert 0 < log[0]["learner_step_fraction"] <= log[1]["learner_step_fraction"] < 1
    dataset = EpisodeStore(tmp_path / "dagger" / "dataset")
    new = [k for k in dataset.keys() if k.startswith("dagger_")]
    assert new and all(dataset.read_with_meta(k)[1]["learner_steps"] >= 0 for k in new)
    assert sum(dataset.read_with_meta(k)[1]["learner_steps"] for k in new) > 0
    # Each record scores its iteration's rollouts (the last one's are all still in the dataset: M 3, N_D 2).
    last = [m for m in map(dataset.read_meta, new) if m["iteration"] == 2]
    assert len(last) == 2 and all(isinstance(m["success"], bool) and isinstance(m["cut"], bool) for m in last)
    assert log[1]["rollout_success"] == sum(m["success"] for m in last) / 2
    assert log[1]["rollout_cut"] == sum(m["cut"] for m in last) / 2
    assert all(0 <= r["rollout_success"] <= 1 and 0 <= r["rollout_cut"] <= 1 for r in log)
    assert len(train) == 4, "discarding from the DAgger dataset never touches the expert store"
    model, *_ = load_checkpoint(checkpoint)
    assert model.kind == "gsmn"
    # `gsmn analyze dagger`, the docs' table of such runs, reads this run as the log and the dataset say.
    script = [sys.executable, "-m", "gsmn.cli", "analyze", "dagger"]
    out = subprocess.run([*script, str(tmp_path / "dagger"), "--dataset"], capture_output=True, text=True,
                         check=True).stdout.splitlines()
    rows = [line.split(" | ") for line in out if line.startswith("| 1 |") or line.startswith("| 2 |")]
    assert [r[1] for r in rows] == ["0.5", "0.25"]
    assert [r[-1].rstrip(" |") for r in rows] == [
        f"{round(r['rollout_success'] * 2)} / {round(r['rollout_cut'] * 2)}" for r in log]
    assert [r[2] for r in rows] == [f"{r['dev']['loss_action']:.3f}" for r in log]
    groups = {"succeeded": [0, 0], "failed and cut": [0, 0], "failed, not cut": [0, 0]}
    for k in new:
        meta, actions = dataset.read_meta(k), dataset.read(k).actions
        group = groups["succeeded" if meta["success"] else "failed and cut" if meta["cut"] else "failed, not cut"]
        group[0] += 1
        group[1] += bool((actions[:, 2] > 0.5).any())
    assert out[-1].endswith(f"3 episodes, {3 - len(new)} from the expert store, {len(new)} rollouts: " + ", ".join(
        f"{name} {n} ({stop} with a STOP label)" for name, (n, stop) in groups.items()))
    # These 20-step rollouts neither arrive nor stray 4.5 m; shares read as counts of the run's N_D (2) rollouts:
    other = tmp_path / "other"
    other.mkdir()
    (other / "config.json").write_text((tmp_path / "dagger" / "config.json").read_text())
    (other / "log.jsonl").write_text(json.dumps({**log[1], "rollout_success": 0.5, "rollout_cut": 1.0}) + "\n")
    out = subprocess.run([*script, str(other)], capture_output=True, text=True, check=True).stdout
    assert out.splitlines()[-1].endswith(" | 1 / 2 |")


def test_dagger_stopped_mid_iteration_resumes_to_the_same_state(stores, supervised_checkpoint, tmp_path):
    train, _ = stores
    whole = train_dagger(tmp_path / "whole", supervised_checkpoint, DAGGER, train, log=lambda s: None)
    stops = iter([True])  # stop at the first saved state inside an epoch, then run to the end
    train_dagger(tmp_path / "parts", supervised_checkpoint, DAGGER, train, log=lambda s: None,
                 stop_after=lambda state: state.batch > 0 and next(stops, False))
    assert not (tmp_path / "parts" / "log.jsonl").is_file() or len(RunFolder(tmp_path / "parts").read_log()) < 2
    p = read_progress(tmp_path / "parts")  # stopped in iteration 1's training: a quarter to half of 2 iterations
    assert p.phase in ("collect", "train") and p.done == 0 and 0.25 <= p.fraction <= 0.5
    # Resumed with another number of rollout workers (rollouts are seeded each, not per worker): nothing changes.
    more_workers = with_overrides(DAGGER, {"dagger.workers": "2"})
    parts = train_dagger(tmp_path / "parts", supervised_checkpoint, more_workers, train, log=lambda s: None)
    a, b = load_file(whole / "weights.safetensors"), load_file(parts / "weights.safetensors")
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_dagger_rollouts_can_be_flown_by_the_mirror_ensemble(supervised_checkpoint, tmp_path):
    """With dagger.mirror_ensemble a rollout worker's learner is the test-time mirror ensemble of the current
    policy: its rollout is the one that ensemble flies (the expert's labels), not the plain network's."""
    from gsmn.model.checkpoint import load_policy
    from gsmn.model.policy import MirrorEnsemble
    from gsmn.task.rollout import task_for_env
    from gsmn.training import dagger
    from gsmn.training.collect import MixturePolicy, record_episode
    from gsmn.world.env import Env

    samples, threads = {}, torch.get_num_threads()
    try:
        for flag in ("false", "true"):  # a worker's two functions, run in this process
            config = with_overrides(DAGGER, {"dagger.mirror_ensemble": flag})
            store = EpisodeStore(tmp_path / flag)
            dagger._init_worker(config, str(store.root), str(supervised_checkpoint))  # sets one torch thread
            try:
                dagger._rollout_one(("r", 2, 1, 0.0, 7))  # beta 0: the learner flies every step
                assert isinstance(dagger._worker["learner"], MirrorEnsemble) == (flag == "true")
            finally:
                dagger._worker["env"].close()
                dagger._worker.clear()
            samples[flag] = store.read("r")
            assert store.read_meta("r")["expert_steps"] == 0
        with Env(DAGGER) as env:  # the same ensemble flown here, on the worker's one thread
            ensemble = MixturePolicy(DAGGER, learner=MirrorEnsemble(load_policy(supervised_checkpoint)), beta=0.0,
                                     max_deviation=DAGGER.dagger.max_deviation)
            expected = record_episode(env, ensemble, task_for_env(2, DAGGER), DAGGER.task.horizon)
    finally:
        torch.set_num_threads(threads)
    assert np.array_equal(samples["true"].images, expected.images)
    assert np.array_equal(samples["true"].actions, expected.actions)
    assert not np.array_equal(samples["true"].images, samples["false"].images), "the ensemble flies otherwise"


def test_a_dagger_rollout_keeps_its_outcome_as_gsmn_eval_scores_it(supervised_checkpoint, tmp_path):
    """A rollout's metadata holds the success `gsmn eval`'s rollout gives the same flight, and whether the
    rollout was cut for straying from the path: the expert alone (beta 1) is the flight `rollout` scores here,
    never cut; the learner's (beta 0) is scored and marked the same way."""
    from gsmn.model.checkpoint import load_policy
    from gsmn.task.baselines import ExpertPolicy
    from gsmn.task.rollout import rollout, task_for_env
    from gsmn.training import dagger
    from gsmn.training.collect import MixturePolicy
    from gsmn.world.env import Env

    config = with_overrides(DAGGER, {"task.horizon": "150"})  # long enough for the expert to arrive
    store, threads = EpisodeStore(tmp_path / "rollouts"), torch.get_num_threads()
    try:
        dagger._init_worker(config, str(store.root), str(supervised_checkpoint))
        try:
            for env_id in (2, 3):
                dagger._rollout_one((f"expert_{env_id}", env_id, 1, 1.0, 7))   # beta 1: the expert every step
                dagger._rollout_one((f"learner_{env_id}", env_id, 1, 0.0, 7))  # beta 0: the learner every step
        finally:
            dagger._worker["env"].close()
            dagger._worker.clear()
        torch.set_num_threads(1)  # as in the worker
        expected = {}
        with Env(config) as env:
            for e in (2, 3):
                task = task_for_env(e, config)
                expected[f"expert_{e}"] = (rollout(env, ExpertPolicy(config), task, config.task.horizon).success, False)
                learner = MixturePolicy(config, learner=load_policy(supervised_checkpoint), beta=0.0,
                                        max_deviation=config.dagger.max_deviation)
                expected[f"learner_{e}"] = (rollout(env, learner, task, config.task.horizon).success, learner.cut)
    finally:
        torch.set_num_threads(threads)
    kept = {k: store.read_meta(k) for k in expected}
    assert {k: (m["success"], m["cut"]) for k, m in kept.items()} == expected
    assert all(expected[f"expert_{e}"][0] for e in (2, 3)), "the expert succeeds here (as on all 500 test ones)"
    assert len({v for v in expected.values()}) > 1, "the outcomes differ, or a constant would pass"


def test_state_killed_between_its_two_renames_is_recovered(tmp_path):
    run = RunFolder(tmp_path / "run")
    model = torch.nn.Linear(2, 2)
    optimizer = torch.optim.Adam(model.parameters())
    run.start(CONFIG)
    run.save_state(model, optimizer, TrainState(epoch=1, step=7))
    run.state_dir.rename(run.root / "state.old")  # as if killed after the first rename, before the second
    assert run.has_state()
    state = run.load_state(torch.nn.Linear(2, 2), torch.optim.Adam(model.parameters()))
    assert (state.epoch, state.step) == (1, 7) and (run.state_dir / "state.json").is_file()


def test_an_epoch_is_logged_only_once_its_state_is_saved(stores, tmp_path, monkeypatch):
    """A monitor (the dashboard) shows each logged record as a saved epoch: a run cancelled between logging and
    saving must not show an epoch it then trains again."""
    train, _ = stores
    seen = []
    save_state = RunFolder.save_state

    def spy(self, model, optimizer, state):
        seen.append((state.epoch, len(self.read_log())))
        save_state(self, model, optimizer, state)

    monkeypatch.setattr(RunFolder, "save_state", spy)
    train_supervised(tmp_path / "run", "gsmn", with_overrides(CONFIG, {"train.epochs": "2"}), train,
                     log=lambda s: None)
    assert all(logged in (epoch - 1, epoch) for epoch, logged in seen), seen
    assert {epoch for epoch, logged in seen if logged == epoch - 1} == {1, 2}, seen  # end-of-epoch saves


def test_a_run_killed_between_its_state_and_its_log_gets_the_record_back(tmp_path):
    run = RunFolder(tmp_path / "run")
    run.start(CONFIG)
    first, second = {"epoch": 1, "train": {"loss": 2.0}}, {"epoch": 2, "train": {"loss": 1.0}}
    run.log(first)
    run.checkpoint_dir.mkdir()
    meta = run.checkpoint_dir / "meta.json"
    meta.write_text(json.dumps({"kind": "gsmn", "metrics": second}))
    run.settle_log(2)  # state saved at 2 epochs, the log one short: the checkpoint (written first) has it
    assert run.read_log() == [first, second]
    run.settle_log(2)
    assert run.read_log() == [first, second]  # nothing twice
    run.settle_log(1)  # a log written ahead of its state (older code): trimmed, the epoch trained again
    assert run.read_log() == [first]
    meta.write_text(json.dumps({"kind": "gsmn", "metrics": {"epoch": 5}}))
    run.settle_log(2)  # a checkpoint of another epoch is not this record
    assert run.read_log() == [first]
    meta.write_bytes(b"\x00\xff{")
    run.settle_log(2)  # damaged: nothing to take back, nothing lost
    assert run.read_log() == [first]


def test_dagger_resumed_without_its_dataset_refills_it_from_the_current_mixture(stores, supervised_checkpoint,
                                                                                 tmp_path):
    """The run's state survives (restored on a new machine), its episodes do not: before the next iteration the run
    flies M rollouts of the current mixture policy into D, says so, and goes on to the end."""
    train, _ = stores
    run = tmp_path / "dagger"
    train_dagger(run, supervised_checkpoint, DAGGER, train, log=lambda s: None,
                 stop_after=lambda state: state.batch == 0 and state.epoch == 1)
    assert len(RunFolder(run).read_log()) == 1
    shutil.rmtree(run / "dataset")
    lines = []
    train_dagger(run, supervised_checkpoint, DAGGER, train, log=lines.append)
    assert any("holds 0 of its 3 episodes; refilling it with 3 rollouts of the current mixture policy (beta 0.25)"
               in line for line in lines)
    log = RunFolder(run).read_log()
    assert [r["iteration"] for r in log] == [1, 2] and "refilled" not in log[0] and log[1]["refilled"] == 3
    dataset = EpisodeStore(run / "dataset")
    assert len(dataset) == 3, "M episodes again after the iteration's discard and rollouts"
    # 3 refills, then the iteration dropped 2 of D's 3 and flew N_D = 2: one refill is left beside the new two
    keys = dataset.keys()
    assert sum(k.startswith("refill_0002_") for k in keys) == 1 and sum(k.startswith("dagger_0002_") for k in keys) == 2
    assert all(m["iteration"] == 2 and m["beta"] == 0.25 for m in map(dataset.read_meta, keys))
