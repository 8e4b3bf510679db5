"""Data-parallel training (`torchrun ... -m gsmn.cli train supervised`, gsmn/training/distributed.py): two gloo
ranks on the CPU take the step one process takes on the same global batch, a killed run resumes, and DAggerFM
runs on two ranks."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from gsmn.config import preset, with_overrides
from gsmn.training import distributed
from gsmn.training.distributed import World
from gsmn.training.store import EpisodeStore
from gsmn.training.supervised import backward, batch_seed, epoch_batches, make_model_and_optimizer, read_batches

pytestmark = pytest.mark.training

FLAGS = {"task.horizon": "20", "train.batch_size": "2", "train.threads": "1"}
TORCHRUN = Path(sys.executable).with_name("torchrun")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _torchrun(data: Path, run: Path, flags: dict) -> list[str]:
    args = [str(TORCHRUN), "--nnodes", "1", "--nproc-per-node", "2", "--master-addr", "127.0.0.1", "--master-port",
            str(_free_port()), "-m", "gsmn.cli", "train", "supervised", "--data", str(data), "--run-dir", str(run),
            "--preset", "tiny"]
    for key, value in flags.items():
        args += ["--" + key.replace("_", "-"), value]
    return args


def failure(stderr: str) -> str:
    """What a failed torchrun says: a rank's Python stacks where it died of a signal (gsmn.training.distributed
    enables faulthandler), then torchrun's report."""
    fatal = stderr.find("Fatal Python error")
    return (stderr[fatal:fatal + 4000] + "\n...\n" if fatal >= 0 else "") + stderr[-3000:]


ENV = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1"}  # loopback only


def test_two_gloo_ranks_take_the_step_one_process_takes_on_the_same_global_batch(stores, tmp_path):
    """One epoch of one global batch of 2 episodes: rank r trains on episode r, its loss weighted by its half of the
    batch, the gradients averaged; one process that adds half of each episode's gradient (each drawn with its
    rank's seed) and steps once ends at the same weights."""
    train, _ = stores
    two = EpisodeStore(tmp_path / "two")
    for key in train.keys()[:2]:
        shutil.copy2(train.path(key), two.path(key))
    flags = {**FLAGS, "train.epochs": "1"}
    run = subprocess.run(_torchrun(two.root, tmp_path / "ddp", flags), env=ENV, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, failure(run.stderr)
    assert len((tmp_path / "ddp" / "log.jsonl").read_text().splitlines()) == 1  # rank 0 alone logs

    config = with_overrides(preset("tiny"), flags)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as each rank: another summation order flips the sign of near-zero gradients
    try:
        model, vocabulary, optimizer = make_model_and_optimizer("gsmn", config, None)
        initial = {k: v.clone() for k, v in model.state_dict().items()}
        (batch,) = epoch_batches(two.keys(), 2, config.train.seed, 0)
        optimizer.zero_grad(set_to_none=True)
        for rank in (0, 1):
            world = World(rank, 2)
            samples = next(read_batches(two, [batch], 0, config.train.mirror, config.train.seed, 0, 0, world))
            assert len(samples) == 1 and world.shard(batch) == ([batch[rank]], 1.0)
            seed = distributed.rank_seed(batch_seed(config.train.seed, 0, 0), world)
            backward(model, samples, vocabulary, config, seed, weight=0.5)
        optimizer.step()  # Adam's first step moves each weight by about lr * sign(gradient)
    finally:
        torch.set_num_threads(threads)
    ddp = load_file(tmp_path / "ddp" / "checkpoint" / "weights.safetensors")
    expected = model.state_dict()
    assert ddp.keys() == expected.keys()
    assert any(not torch.equal(expected[k], initial[k]) for k in expected)  # a step was taken
    for key, value in expected.items():
        torch.testing.assert_close(ddp[key], value, rtol=1e-5, atol=1e-6, msg=key)


def test_a_killed_two_rank_run_resumes_to_the_state_of_an_uninterrupted_one(stores, tmp_path):
    train, _ = stores
    flags = {**FLAGS, "train.epochs": "3", "train.save_every_seconds": "0"}
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    done = subprocess.run(_torchrun(train.root, whole, flags), env=ENV, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, failure(done.stderr)
    proc = subprocess.Popen(_torchrun(train.root, killed, flags), env=ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)  # its own group: torchrun and ranks
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            try:
                if json.loads((killed / "state" / "state.json").read_text())["step"] >= 3:
                    break
            except (OSError, json.JSONDecodeError, KeyError):
                pass  # not yet written, or caught mid-rename
            assert proc.poll() is None, "the run finished before it could be killed"
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGKILL)  # torchrun and both ranks at once
    finally:
        proc.wait()
    assert json.loads((killed / "state" / "state.json").read_text())["epoch"] < 3
    resumed = subprocess.run(_torchrun(train.root, killed, flags), env=ENV, capture_output=True, text=True,
                             timeout=600)
    assert resumed.returncode == 0, failure(resumed.stderr)
    a = load_file(whole / "checkpoint" / "weights.safetensors")
    b = load_file(killed / "checkpoint" / "weights.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    log_a = [json.loads(x) for x in (whole / "log.jsonl").read_text().splitlines()]
    log_b = [json.loads(x) for x in (killed / "log.jsonl").read_text().splitlines()]
    assert [x["epoch"] for x in log_b] == [1, 2, 3]
    assert [x["train"]["loss"] for x in log_a] == [x["train"]["loss"] for x in log_b]


def test_dagger_on_two_ranks_flies_on_rank_0_and_trains_on_both(stores, tmp_path):
    """`torchrun ... train dagger`: rank 0 flies each iteration's rollouts while the other waits, then both train
    its epoch; two iterations finish with the dataset at M episodes and one log line each."""
    from gsmn.training.supervised import train_supervised

    train, _ = stores
    flags = {**FLAGS, "train.epochs": "1", "dagger.iterations": "2", "dagger.rollouts_per_iteration": "2",
             "dagger.dataset_size": "3", "dagger.workers": "1"}
    init = train_supervised(tmp_path / "sup", "gsmn", with_overrides(preset("tiny"), flags), train, log=lambda s: None)
    args = _torchrun(train.root, tmp_path / "dagger", flags)
    args[args.index("supervised")] = "dagger"
    run = subprocess.run(args + ["--init", str(init)], env=ENV, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, failure(run.stderr)
    log = [json.loads(x) for x in (tmp_path / "dagger" / "log.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in log] == [1, 2] and all(r["dataset"] == 3 for r in log)
    dataset = EpisodeStore(tmp_path / "dagger" / "dataset")
    assert len(dataset) == 3 and any(k.startswith("dagger_0002_") for k in dataset.keys())
