"""Supervised learning on expert episodes with every objective (paper: Learning, Auxiliary Objectives;
Hyper-parameters: Adam, lr 0.001, L2 1e-6).

One `train_step` and a short loop over epochs. Validation on the dev store after every epoch logs the
loss terms and the accuracies the paper plots (its Figure 4). Every random choice of a batch (episode
order, dropout, sampled negative goal cells) is seeded from (seed, epoch, batch), so a run killed at any
point and resumed from its saved state trains exactly as an uninterrupted one.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import closing
from pathlib import Path

import numpy as np
import torch

from gsmn.config import RunConfig
from gsmn.model.batch import collate
from gsmn.model.checkpoint import CheckpointError, load_checkpoint, load_optimizer_state, save_checkpoint, with_model_of
from gsmn.model.fpv import freeze_all_but_memory
from gsmn.model.losses import compute_losses
from gsmn.model.models import Model, build_model, forward_batch
from gsmn.model.runtime import set_torch_threads
from gsmn.model.vocabulary import Vocabulary
from gsmn.training import distributed
from gsmn.training.augment import maybe_mirror
from gsmn.training.distributed import SINGLE, World
from gsmn.training.run import RunFolder, TrainState
from gsmn.training.store import EpisodeStore

Logger = Callable[[str], None]
Progress = Callable[[dict], None]  # called with the same dict the run folder's progress.json records


def batch_seed(seed: int, epoch: int, batch: int) -> int:
    return int(np.random.SeedSequence([seed, epoch, batch]).generate_state(1)[0])


def epoch_batches(keys: list[str], batch_size: int, seed: int, epoch: int) -> list[list[str]]:
    """The episodes of each batch of an epoch, shuffled by (seed, epoch)."""
    order = np.random.default_rng(np.random.SeedSequence([seed, epoch])).permutation(len(keys))
    return [[keys[i] for i in order[k:k + batch_size]] for k in range(0, len(keys), batch_size)]


def read_batches(store: EpisodeStore, batches: list[list[str]], start: int, mirror: float, seed: int, epoch: int,
                 prefetch: int = 0, world: World = SINGLE) -> Iterator[list]:
    """The episodes of batches[start:], each batch mirrored as its seed says, in order. With `prefetch` > 0 that
    many threads read up to 2 * prefetch batches ahead of the one being trained on, so reading overlaps training;
    the batches are the same either way. The threads share the GIL with the training loop: decompressing and
    flipping arrays release it, the rest does not (worker processes, tried, cost more than they saved here:
    docs/design.md, "Reading ahead"). With several ranks (`gsmn.training.distributed`), this rank's shard of each
    batch."""
    def load(i: int) -> list:
        if world.size <= 1:
            return maybe_mirror([store.read(key) for key in batches[i]], mirror, batch_seed(seed, epoch, i))
        keys, _ = world.shard(batches[i])
        return maybe_mirror([store.read(key) for key in keys], mirror, batch_seed(seed, epoch, i),
                            world.positions(len(batches[i])), len(batches[i]))

    if prefetch <= 0:
        for i in range(start, len(batches)):
            yield load(i)
        return
    pool = ThreadPoolExecutor(prefetch, thread_name_prefix="gsmn-read")
    pending: deque[Future] = deque()
    try:
        following = start
        while following < len(batches) or pending:
            while following < len(batches) and len(pending) < 2 * prefetch:
                pending.append(pool.submit(load, following))
                following += 1
            yield pending.popleft().result()
    finally:  # also when the caller stops early: no reads left running
        pool.shutdown(wait=True, cancel_futures=True)


def train_step(model: Model, optimizer: torch.optim.Optimizer, samples: list, vocabulary: Vocabulary,
               config: RunConfig, seed: int, weight: float = 1.0, world: World = SINGLE) -> dict[str, float]:
    """One optimizer step on a batch of episodes; returns the loss terms and accuracies as floats. On several
    ranks, `samples` is this rank's shard, its loss weighted by `weight` and the gradients averaged over the
    ranks before the step (`gsmn.training.distributed`)."""
    optimizer.zero_grad(set_to_none=True)
    values = backward(model, samples, vocabulary, config, seed, weight)
    distributed.average_gradients(model, world)
    optimizer.step()
    return values


def backward(model: Model, samples: list, vocabulary: Vocabulary, config: RunConfig, seed: int,
             weight: float = 1.0) -> dict[str, float]:
    """The loss of a batch, its gradient (times `weight`) added to the parameters'; returns the loss terms and
    accuracies (unweighted) as floats."""
    device = model_device(model)
    torch.manual_seed(seed)  # dropout (on every device)
    generator = torch.Generator(device=device).manual_seed(seed)  # pose noise, sampled negatives
    batch = collate(samples, vocabulary).to(device)
    model.train()
    outputs = forward_batch(model, batch, generator=generator)
    losses = compute_losses(model, batch, outputs, config.loss, generator=generator)
    (losses.total if weight == 1.0 else losses.total * weight).backward()
    return flatten(losses, frames=int(batch.mask.sum()))


def model_device(model: torch.nn.Module) -> torch.device:
    return next(model.parameters()).device


def training_device(name: str) -> torch.device:
    """The torch device `train.device` names, refused with a clear message where this machine has none."""
    device = torch.device(name)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"--train.device {name}: torch {torch.__version__} sees no CUDA device on this machine "
                             "(use --train.device cpu)")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"--train.device {name}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return device


def flatten(losses, frames: int) -> dict[str, float]:
    out = {"loss": float(losses.total.detach()), "frames": float(frames)}
    out.update({f"loss_{k}": float(v.detach()) for k, v in losses.terms.items()})
    out.update({f"acc_{k}": v for k, v in losses.accuracies.items()})
    return out


@torch.inference_mode()
def validate(model: Model, store: EpisodeStore, vocabulary: Vocabulary, config: RunConfig,
             batch_size: int, seed: int = 0) -> dict[str, float]:
    """Mean loss terms and accuracies over a store, in eval mode, with fixed sampled negatives."""
    model.eval()
    device = model_device(model)
    sums: dict[str, float] = {}
    counts: dict[str, int] = {}
    keys = store.keys()
    for k in range(0, len(keys), batch_size):
        generator = torch.Generator(device=device).manual_seed(seed + k)
        batch = collate([store.read(key) for key in keys[k:k + batch_size]], vocabulary).to(device)
        outputs = forward_batch(model, batch, generator=generator)
        _accumulate(sums, counts, flatten(compute_losses(model, batch, outputs, config.loss, generator=generator),
                                          frames=int(batch.mask.sum())))
    return _means(sums, counts)


SUMMED = ("frames", "seconds")  # totals over an epoch; everything else is a mean over batches


def _accumulate(sums: dict[str, float], counts: dict[str, int], values: dict[str, float]) -> None:
    for name, value in values.items():
        if name in SUMMED:
            sums[name], counts[name] = sums.get(name, 0.0) + value, 1
        elif not math.isnan(value):
            sums[name] = sums.get(name, 0.0) + value
            counts[name] = counts.get(name, 0) + 1


def _means(sums: dict[str, float], counts: dict[str, int]) -> dict[str, float]:
    return {name: sums[name] / counts[name] for name in sums}


def make_model_and_optimizer(kind: str, config: RunConfig, init: Path | None, init_optimizer: bool = False
                             ) -> tuple[Model, Vocabulary, torch.optim.Optimizer]:
    """The model (from `init`'s weights, or fresh from the config's seed) and its Adam. With `init_optimizer`,
    Adam starts from the state saved in `init` (its moments and step counts), with this config's learning rate
    and weight decay."""
    device = training_device(config.train.device)
    if init is not None:
        model, _, vocabulary, _ = load_checkpoint(init, device=device)
        if model.kind != kind:
            raise ValueError(f"--init {init} holds a {model.kind!r} model, not {kind!r}")
    else:
        vocabulary = Vocabulary.default()
        torch.manual_seed(config.train.seed)  # the initial weights, too, are a function of the config
        model = build_model(kind, config, vocabulary).to(device)  # built on the CPU: the same weights everywhere
    lr, decay = config.train.learning_rate, config.train.weight_decay
    if config.train.trainable == "memory":
        lstm, masked = freeze_all_but_memory(model)  # the masked weights' frozen entries need no weight decay
        optimizer = torch.optim.Adam([{"params": lstm}, {"params": masked, "weight_decay": 0.0, "masked": True}],
                                     lr=lr, weight_decay=decay)
    else:
        optimizer = torch.optim.Adam(model.parameters(), lr=lr, weight_decay=decay)
    if init_optimizer:
        if init is None:
            raise ValueError("init_optimizer needs a checkpoint to start from (--init)")
        saved = load_optimizer_state(init)
        try:
            optimizer.load_state_dict(saved)
        except ValueError as e:  # parameter groups or sizes that do not match this model
            raise CheckpointError(f"checkpoint {init}: its optimizer state does not fit the model ({e})") from e
        for group in optimizer.param_groups:
            group.update(lr=lr, weight_decay=0.0 if group.get("masked") else decay)
    return model, vocabulary, optimizer


def run_epoch(run: RunFolder, model: Model, optimizer: torch.optim.Optimizer, vocabulary: Vocabulary,
              config: RunConfig, store: EpisodeStore, keys: list[str], state: TrainState, epoch: int,
              stop_after: Callable[[TrainState], bool] | None = None, on_progress: Progress | None = None,
              progress: dict | None = None, world: World = SINGLE) -> bool:
    """Train on the batches of `epoch` from `state.batch` on, saving state every `save_every_seconds`.
    Returns False when `stop_after` ended it early (state saved), True when the epoch is done.
    After each batch, `progress` (e.g. {"phase": "train", "epoch": 3}) plus the batch counters and the batch's
    loss is written to the run's progress.json (throttled) and passed to `on_progress`. On several ranks each
    trains on its shard of every batch, rank 0 alone writes, and all save (and stop) at rank 0's word."""
    tc = config.train
    batches = epoch_batches(keys, tc.batch_size, tc.seed, epoch)
    progress = {"phase": "train", **(progress or {"epoch": epoch + 1})}
    last_save = time.monotonic()
    with closing(read_batches(store, batches, state.batch, tc.mirror, tc.seed, epoch, tc.prefetch, world)) as reader:
        t0 = time.monotonic()  # a batch's seconds count the wait for its episodes, as without prefetching
        for samples in reader:
            seed = distributed.rank_seed(batch_seed(tc.seed, epoch, state.batch), world)
            weight = world.shard(batches[state.batch])[1] if world.size > 1 else 1.0
            values = train_step(model, optimizer, samples, vocabulary, config, seed, weight, world)
            values["seconds"] = time.monotonic() - t0
            _accumulate(state.sums, state.counts, values)
            state.batch += 1
            state.step += 1
            state.seconds += values["seconds"]
            now = {**progress, "batch": state.batch, "batches": len(batches), "step": state.step,
                   "loss": values.get("loss"), "frames": values.get("frames")}
            if world.main:
                run.write_progress(now, force=state.batch == len(batches))
                if on_progress:
                    on_progress(now)
            due = time.monotonic() - last_save >= tc.save_every_seconds and state.batch < len(batches)
            if distributed.agree(due, world, model_device(model)):
                if world.main:
                    run.save_state(model, optimizer, state)
                distributed.barrier(world)
                last_save = time.monotonic()
                if distributed.agree(bool(world.main and stop_after and stop_after(state)), world, model_device(model)):
                    return False
            t0 = time.monotonic()
    return True


def start_or_resume(run: RunFolder, kind: str, config: RunConfig, init: Path | None, init_optimizer: bool
                    ) -> tuple[Model, Vocabulary, torch.optim.Optimizer, TrainState | None]:
    """The model, vocabulary and Adam of a run, and its saved state when it has one (None for a new run). A run
    resuming from its own state takes weights and Adam from there, so `init`'s optimizer state is read only for a
    new run (the checkpoint may have been replaced since, e.g. by one without it)."""
    resuming = run.has_state()
    model, vocabulary, optimizer = make_model_and_optimizer(kind, config, init, init_optimizer and not resuming)
    return model, vocabulary, optimizer, run.load_state(model, optimizer) if resuming else None


def finish_epoch(run: RunFolder, model: Model, optimizer: torch.optim.Optimizer, vocabulary: Vocabulary,
                 config: RunConfig, state: TrainState, record: dict, dev_store: EpisodeStore | None,
                 log: Logger, world: World = SINGLE) -> None:
    """Validate, log, write the checkpoint, and save the state of the next epoch (rank 0; the other ranks only
    count the epoch, and all go on together)."""
    if not world.main:
        state.epoch, state.batch, state.sums, state.counts = state.epoch + 1, 0, {}, {}
        distributed.barrier(world)
        return
    record.update(step=state.step, seconds=round(state.seconds, 1), train=_means(state.sums, state.counts))
    if config.train.mirror:
        record["mirror"] = config.train.mirror
    if dev_store is not None and len(dev_store):
        record["dev"] = validate(model, dev_store, vocabulary, config, config.train.batch_size)
    log(_summary_line(record))
    save_checkpoint(run.checkpoint_dir, model, config, vocabulary, meta={"step": state.step, "metrics": record},
                    optimizer_state=optimizer.state_dict())
    state.epoch, state.batch, state.sums, state.counts = state.epoch + 1, 0, {}, {}
    run.save_state(model, optimizer, state)
    run.log(record)  # last: a record in the log is an epoch saved, which a monitor may show as kept
    distributed.barrier(world)


def train_supervised(run_dir: Path | str, kind: str, config: RunConfig, train_store: EpisodeStore,
                     dev_store: EpisodeStore | None = None, init: Path | None = None,
                     log: Logger = print, stop_after: Callable[[TrainState], bool] | None = None,
                     on_progress: Progress | None = None, init_optimizer: bool = False,
                     on_epoch: Callable[[TrainState], None] | None = None) -> Path:
    """Train (or resume training) `kind` on `train_store`; returns the checkpoint folder. With `init_optimizer`,
    a new run's Adam starts from the optimizer state saved in the checkpoint `init`. `on_epoch(state)` is called
    after each finished epoch, once its checkpoint and state are saved.

    `stop_after(state)` is asked after every saved state and may end the call early (the run stays
    resumable); tests use it, the command line does not.

    Started by torchrun with several processes, each is one rank of a data-parallel run
    (`gsmn.training.distributed`): rank 0 alone writes the run folder, which every rank must see."""
    set_torch_threads(config.train.threads)
    world = distributed.init(config.train.device)
    if init is not None:
        config = with_model_of(config, init)
    run = RunFolder(run_dir)
    if world.main:
        run.start(config)
    distributed.barrier(world)
    config = on_rank_device(config, world)
    model, vocabulary, optimizer, state = start_or_resume(run, kind, config, init, init_optimizer)
    state = TrainState() if state is None else state
    if world.main:
        run.settle_log(state.epoch)
    keys = train_store.keys()
    if not keys:
        raise ValueError(f"no episodes in {train_store.root}; collect some with `gsmn collect`")
    check_batch_size(config, world)
    while state.epoch < config.train.epochs:
        if not run_epoch(run, model, optimizer, vocabulary, config, train_store, keys, state, state.epoch, stop_after,
                         on_progress, {"epoch": state.epoch + 1, "epochs": config.train.epochs}, world):
            return run.checkpoint_dir
        if world.main:
            run.write_progress({"phase": "validate", "epoch": state.epoch + 1, "epochs": config.train.epochs},
                               force=True)
        finish_epoch(run, model, optimizer, vocabulary, config, state, {"epoch": state.epoch + 1}, dev_store, log,
                     world)
        if on_epoch and world.main:
            on_epoch(state)
        if distributed.agree(bool(world.main and stop_after and stop_after(state)), world, model_device(model)):
            break
    if state.epoch >= config.train.epochs and world.main:
        run.write_progress({"phase": "done", "epoch": state.epoch, "epochs": config.train.epochs}, force=True)
    return run.checkpoint_dir


def check_batch_size(config: RunConfig, world: World) -> None:
    if config.train.batch_size < world.size:
        raise ValueError(f"--train.batch-size {config.train.batch_size} is the global batch, split over the "
                         f"{world.size} ranks: give at least {world.size} (a multiple keeps every rank busy)")


def on_rank_device(config: RunConfig, world: World) -> RunConfig:
    """The config this rank computes with: on CUDA, its own GPU (the run folder records rank 0's)."""
    import dataclasses

    device = distributed.device_for(world, config.train.device)
    if device == config.train.device:
        return config
    return dataclasses.replace(config, train=dataclasses.replace(config.train, device=device))


def _summary_line(record: dict) -> str:
    def part(name: str, values: dict) -> str:
        accs = " ".join(f"{k[4:]} {100 * v:.0f}%" for k, v in values.items() if k.startswith("acc_"))
        return f"{name}: loss {values.get('loss', float('nan')):.4f} action {values.get('loss_action', 0):.4f} {accs}"

    train = record["train"]
    fps = train.get("frames", 0) / max(train.get("seconds", 0), 1e-9)
    head = ", ".join(f"{k} {v}" for k, v in record.items() if k in ("epoch", "iteration", "beta", "dataset"))
    line = f"{head} ({train.get('seconds', 0):.0f} s, {fps:.0f} frames/s) " + part("train", train)
    if "dev" in record:
        line += " | " + part("dev", record["dev"])
    return line
