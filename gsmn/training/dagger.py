"""DAggerFM: DAgger with a fixed-size dataset (paper: Learning, Algorithm 1).

    D <- M episodes sampled from the expert data D*;  pi_1 <- the supervised policy (--init)
    for i = 1..K:
        discard N_D episodes of D uniformly at random
        beta <- beta0 ** i;  pi_hat_i <- per step, the expert with probability beta, else pi_i
        D_i <- N_D rollouts of pi_hat_i, labelled by the expert;  D <- D u D_i
        pi_{i+1} <- one epoch on D (the optimizer's state carries over: the original rebuilt it, losing it)

Rollouts fly in parallel worker processes (or Ray actors: `gsmn.executor`) that load the current policy from
`run/policy/` (a checkpoint written before each collection; on Ray its files go through the object store once);
a rollout is cut when the drone strays 4.5 m from the path. With `dagger.mirror_ensemble` the learner flies as
a test-time mirror ensemble (`gsmn.model.policy.MirrorEnsemble`; not in the paper), so that the rollouts visit
the states of the policy as it is deployed; one network is trained. The run is resumable after a kill at any
point: each phase writes down what it will do (the keys to discard, the rollouts to fly) in the saved state
before doing it, episodes are written atomically, and the
epoch resumes batch by batch as in supervised training. A run resumed from its saved state without its dataset
(the state restored on a new machine, the episodes gone) first refills D to M episodes with rollouts of the current
mixture policy, and says so in its log (not in Algorithm 1: docs/design.md).

Each iteration's log record has, beside the dev figures on expert states, the closed loop of its own rollouts:
`rollout_success`, the share of them that ended in success as `gsmn eval` scores it, and `rollout_cut`, the
share cut for straying from the path. Once beta is near 0 these are the current policy's flights in fresh
environments, seen for free (N_D of them: noisy from one iteration to the next, a trend over several).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from gsmn.config import RunConfig
from gsmn.executor import Executor, ExecutorOptions, make_executor, open_shared, shared_key
from gsmn.model.checkpoint import load_policy, read_checkpoint_kind, save_checkpoint, with_model_of
from gsmn.model.policy import MirrorEnsemble
from gsmn.model.runtime import set_torch_threads
from gsmn.model.vocabulary import Vocabulary
from gsmn.task.rollout import task_for_env
from gsmn.training import distributed
from gsmn.training.collect import MixturePolicy, fly_and_record
from gsmn.training.run import RunFolder, TrainState
from gsmn.training.store import EpisodeStore
from gsmn.training.supervised import (
    Logger,
    Progress,
    check_batch_size,
    finish_epoch,
    make_model_and_optimizer,
    model_device,
    on_rank_device,
    run_epoch,
    start_or_resume,
)
from gsmn.world.env import Env


def beta_schedule(beta0: float, iteration: int) -> float:
    """beta_i = beta0 ** i for iteration i = 1, 2, ... (the original's 0.92 ** (i + 1) counted from 0)."""
    return beta0**iteration


def _rng(seed: int, *keys: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, *keys]))


# -- rollout workers --------------------------------------------------------------------------------
_worker: dict = {}


def _init_worker(config: RunConfig, dataset_root: str, policy_dir: str) -> None:
    set_torch_threads(1)
    _worker.update(config=config, env=Env(config), store=EpisodeStore(dataset_root), policy_dir=policy_dir,
                   iteration=None, learner=None)


def _rollout_one(job: tuple[str, int, int, float, int], policy=None) -> tuple[str, int, int]:
    """Fly one mixture rollout and write it; returns (key, expert steps, learner steps). `policy`: the
    executor's handle to the current policy checkpoint (`gsmn.executor.share`; default: the worker's
    `policy_dir`)."""
    key, env_id, iteration, beta, seed = job
    w = _worker
    config: RunConfig = w["config"]
    source = w["policy_dir"] if policy is None else policy
    if w["iteration"] != (iteration, shared_key(source)):  # the policy changes once per iteration
        learner = load_policy(open_shared(source))
        w["learner"] = MirrorEnsemble(learner) if config.dagger.mirror_ensemble else learner
        w["iteration"] = (iteration, shared_key(source))
    policy = MixturePolicy(config, learner=w["learner"], beta=beta, rng=_rng(seed),
                           max_deviation=config.dagger.max_deviation)
    sample, record = fly_and_record(w["env"], policy, task_for_env(env_id, config), config.task.horizon)
    w["store"].write(key, sample, meta={"env_id": env_id, "iteration": iteration, "beta": beta,
                                        "expert_steps": policy.expert_steps, "learner_steps": policy.learner_steps,
                                        "success": record.success, "cut": policy.cut})
    return key, policy.expert_steps, policy.learner_steps


# -- the algorithm ----------------------------------------------------------------------------------
@dataclass
class _Run:
    """What the phases of one DAggerFM run share. `state.extra["phase"]` names the phase to do next (start,
    refill, discard, collect, train) and what it will do, saved before it is done."""

    run: RunFolder
    config: RunConfig  # this rank's (`on_rank_device`)
    world: distributed.World
    model: torch.nn.Module
    vocabulary: Vocabulary
    optimizer: torch.optim.Optimizer
    state: TrainState | None  # None on the other ranks until they follow rank 0's saved state
    dataset: EpisodeStore  # D
    log: Logger
    on_progress: Progress | None
    executor_options: ExecutorOptions | None
    env_ids: list[int] = field(default_factory=list)  # where rollouts are drawn
    expected: int = 0  # the episodes D holds from the start on (M, or all the expert episodes where fewer)
    pool: Executor | None = None  # the rollout workers, started at the first rollouts

    def save(self, extra: dict) -> None:
        """Write down the next phase, and what it will do, in the saved state (before doing it)."""
        self.state.extra = extra
        self.run.save_state(self.model, self.optimizer, self.state)

    def report(self, progress: dict, force: bool = False) -> None:
        self.run.write_progress(progress, force=force)
        if self.on_progress:
            self.on_progress(progress)

    def fly(self, jobs: list) -> Iterator[int]:
        """Fly mixture rollouts (`_rollout_one`) on the workers, counting them as they land."""
        self.pool = self.pool or _make_pool(self.config, self.dataset, self.run.root / "policy",
                                            self.executor_options)
        shared = self.pool.share(self.run.root / "policy")  # the weights once per phase, not with each rollout
        for k, _ in enumerate(self.pool.map(_rollout_one, jobs, shared), start=1):
            yield k


def train_dagger(run_dir: Path | str, init: Path, config: RunConfig, expert_store: EpisodeStore,
                 dev_store: EpisodeStore | None = None, env_ids: list[int] | None = None, log: Logger = print,
                 stop_after: Callable[[TrainState], bool] | None = None, on_progress: Progress | None = None,
                 init_optimizer: bool = False, on_iteration: Callable[[TrainState], None] | None = None,
                 executor_options: ExecutorOptions | None = None) -> Path:
    """Run (or resume) DAggerFM from the checkpoint `init`; returns the final checkpoint folder.

    Rollouts are drawn from `env_ids` (default: the environments of the expert store). With `init_optimizer`,
    Adam starts from the optimizer state saved in `init` (a run continued from an earlier run's checkpoint keeps
    its optimizer, as Algorithm 1's iterations do), else fresh. `on_iteration(state)` is called after each finished
    iteration, once its checkpoint and state are saved (e.g. to keep a copy of that stage elsewhere).
    `executor_options`: where the rollouts fly (default: `dagger.workers` processes on this host; `gsmn.executor`)."""
    d = _resume(run_dir, init, config, log, on_progress, init_optimizer, executor_options)
    expert_keys = expert_store.keys()
    _choose_environments(d, expert_store, expert_keys, env_ids)
    if d.world.main and d.state.extra["phase"] == "start":
        _seed_dataset(d, expert_store, expert_keys)
    if d.world.size > 1:
        d.state = _follow(d.run, d.model, d.optimizer, d.world, d.state if d.world.main else None)
    iterations = d.config.dagger.iterations
    try:
        while d.state.epoch < iterations:
            i = d.state.epoch + 1  # iteration index, from 1
            beta = beta_schedule(d.config.dagger.beta0, i)
            _collect_with_current_policy(d, i, beta)
            if not _train_iteration(d, i, beta, dev_store, stop_after, on_iteration):
                break  # stopped mid-epoch (its state saved) or at an iteration's end
    finally:
        if d.pool is not None:  # stopped early: finish the rollouts in flight (written atomically), start no more
            d.pool.close()
    if d.state.epoch >= iterations and d.world.main:
        d.report({"phase": "done", "iteration": d.state.epoch, "iterations": iterations}, force=True)
    return d.run.checkpoint_dir


def _resume(run_dir: Path | str, init: Path, config: RunConfig, log: Logger,
            on_progress: Progress | None, init_optimizer: bool, executor_options: ExecutorOptions | None) -> _Run:
    """The run folder started (or found), and the model, vocabulary and Adam of `init` or of the run's saved state:
    rank 0 reads that state (a new run starts at phase "start"); the other ranks follow it later (`_follow`)."""
    set_torch_threads(config.train.threads)
    kind = read_checkpoint_kind(init)  # first: a folder that is no checkpoint gets the clearest message
    config = with_model_of(config, init)
    world = distributed.init(config.train.device)
    run = RunFolder(run_dir)
    if world.main:
        run.start(config)
    distributed.barrier(world)
    config = on_rank_device(config, world)
    check_batch_size(config, world)
    dataset = EpisodeStore(run.root / "dataset")
    state = None
    if world.main:
        model, vocabulary, optimizer, state = start_or_resume(run, kind, config, init, init_optimizer)
        state = TrainState(epoch=0, extra={"phase": "start"}) if state is None else state
        run.settle_log(state.epoch)
    else:  # the weights, Adam and counters come from rank 0's saved state (`_follow`)
        model, vocabulary, optimizer = make_model_and_optimizer(kind, config, init)
    return _Run(run, config, world, model, vocabulary, optimizer, state, dataset, log, on_progress,
                executor_options)


def _choose_environments(d: _Run, expert_store: EpisodeStore, expert_keys: list[str],
                         env_ids: list[int] | None) -> None:
    """Where the rollouts fly (`env_ids`, else the expert store's environments), and how many episodes D holds."""
    if env_ids is None:
        env_ids = sorted({expert_store.read_meta(k).get("env_id", -1) for k in expert_keys} - {-1})
    if not env_ids:
        raise ValueError("no environments to roll out in: give env_ids or an expert store with env ids")
    d.env_ids = env_ids
    # D holds M episodes from the start on (each iteration drops N_D and adds N_D); a run resumed without its
    # dataset (a new machine: the run's state restored, its episodes gone) refills it before the next iteration
    dataset_size = d.config.dagger.dataset_size
    d.expected = min(dataset_size, len(expert_keys)) if expert_keys else dataset_size


def _seed_dataset(d: _Run, expert_store: EpisodeStore, expert_keys: list[str]) -> None:
    """D ~ D*: M episodes of the expert data (hard links: no copy of the data)."""
    size = min(d.config.dagger.dataset_size, len(expert_keys))
    chosen = _rng(d.config.train.seed, 0).choice(len(expert_keys), size=size, replace=False)
    for i in sorted(chosen):
        _link(expert_store.path(expert_keys[i]), d.dataset.path(expert_keys[i]))
    d.save({"phase": "discard"})


def _collect_with_current_policy(d: _Run, i: int, beta: float) -> None:
    """Rank 0's phases before iteration `i`'s epoch, each taken up where a stopped run left it: refill a lost D,
    choose what to discard and where to fly, then discard and fly; the other ranks wait and follow its state."""
    if d.world.main and d.state.extra["phase"] == "discard" and len(d.dataset) < d.expected:  # lost (a new machine)
        _plan_refill(d, i, beta)
    if d.world.main and d.state.extra["phase"] == "refill":
        _refill(d, i, beta)
    if d.world.main and d.state.extra["phase"] == "discard":
        _plan_iteration(d, i, beta)
    if d.world.main and d.state.extra["phase"] == "collect":
        _discard_and_collect(d, i, beta)
    if d.world.size > 1:  # the other ranks wait while rank 0 collects, then train from its saved state
        d.state = _follow(d.run, d.model, d.optimizer, d.world, d.state if d.world.main else None)


def _plan_refill(d: _Run, i: int, beta: float) -> None:
    """The rollouts of the current mixture policy, labelled by the expert, that refill D to its M episodes."""
    missing = d.expected - len(d.dataset)
    rng = _rng(d.config.train.seed, i, 1)
    jobs = [(f"refill_{i:04d}_{k:03d}_env_{e:06d}", int(e), i, beta, int(rng.integers(2**31)))
            for k, e in enumerate(rng.choice(d.env_ids, size=missing, replace=True))]
    d.log(f"iteration {i}: the dataset holds {len(d.dataset)} of its {d.expected} episodes; refilling it with "
          f"{missing} rollouts of the current mixture policy (beta {beta:.4g}), labelled by the expert")
    d.save({"phase": "refill", "jobs": jobs})


def _refill(d: _Run, i: int, beta: float) -> None:
    """Fly the refill's rollouts not yet in D."""
    save_checkpoint(d.run.root / "policy", d.model, d.config, d.vocabulary, meta={"iteration": i})
    todo = [tuple(j) for j in d.state.extra["jobs"] if j[0] not in d.dataset]
    if todo:
        for k in d.fly(todo):
            d.report({"phase": "collect", "iteration": i, "iterations": d.config.dagger.iterations,
                      "beta": round(beta, 4), "rollouts": len(todo), "done": k})
    d.save({"phase": "discard", "refilled": len(d.state.extra["jobs"])})


def _plan_iteration(d: _Run, i: int, beta: float) -> None:
    """The N_D episodes of D to discard, uniformly at random, and the N_D rollouts to fly (environment, seed)."""
    n = d.config.dagger.rollouts_per_iteration
    refilled = d.state.extra.get("refilled", 0)
    keys = d.dataset.keys()
    rng = _rng(d.config.train.seed, i)
    drop = [keys[j] for j in rng.choice(len(keys), size=min(n, len(keys)), replace=False)]
    new_envs = [int(e) for e in rng.choice(d.env_ids, size=n, replace=True)]
    jobs = [(f"dagger_{i:04d}_{k:03d}_env_{e:06d}", e, i, beta, int(rng.integers(2**31)))
            for k, e in enumerate(new_envs)]
    d.save({"phase": "collect", "drop": drop, "jobs": jobs, "refilled": refilled})


def _discard_and_collect(d: _Run, i: int, beta: float) -> None:
    """Discard the chosen episodes and add the rollouts of pi_hat_i (D <- D u D_i), those not flown yet."""
    extra = d.state.extra
    for key in extra["drop"]:
        d.dataset.delete(key)
    save_checkpoint(d.run.root / "policy", d.model, d.config, d.vocabulary, meta={"iteration": i})
    todo = [tuple(j) for j in extra["jobs"] if j[0] not in d.dataset]
    n_jobs = len(extra["jobs"])
    collect = {"phase": "collect", "iteration": i, "iterations": d.config.dagger.iterations, "beta": round(beta, 4),
               "rollouts": n_jobs}
    d.report({**collect, "done": n_jobs - len(todo)}, force=True)
    if todo:
        for k in d.fly(todo):
            d.report({**collect, "done": n_jobs - len(todo) + k})
    d.save({"phase": "train", "mix": _mixture_counts(d.dataset, extra["jobs"]),
            "refilled": extra.get("refilled", 0)})


def _train_iteration(d: _Run, i: int, beta: float, dev_store: EpisodeStore | None,
                     stop_after: Callable[[TrainState], bool] | None,
                     on_iteration: Callable[[TrainState], None] | None) -> bool:
    """One epoch on D (pi_{i+1}), then validation, the log record, the checkpoint and the next iteration's saved
    state, and `on_iteration`. False where the run stops: mid-epoch, or at its end (`stop_after`)."""
    if d.state.extra["phase"] != "train":
        return True
    iterations = d.config.dagger.iterations
    if not run_epoch(d.run, d.model, d.optimizer, d.vocabulary, d.config, d.dataset, d.dataset.keys(), d.state, i,
                     stop_after, d.on_progress, {"iteration": i, "iterations": iterations}, d.world):
        return False
    if d.world.main:
        d.report({"phase": "validate", "iteration": i, "iterations": iterations}, force=True)
    record = _iteration_record(d, i, beta)
    d.state.extra = {"phase": "discard"}
    finish_epoch(d.run, d.model, d.optimizer, d.vocabulary, d.config, d.state, record, dev_store, d.log, d.world)
    if on_iteration and d.world.main:
        on_iteration(d.state)
    stop = bool(d.world.main and stop_after and stop_after(d.state))
    return not distributed.agree(stop, d.world, model_device(d.model))


def _iteration_record(d: _Run, i: int, beta: float) -> dict:
    """The iteration's log record beside the dev figures: beta, D's size, the learner's share of the steps flown,
    and the closed loop of its own rollouts (and how many refilled a lost D)."""
    mix = d.state.extra["mix"]
    record = {"iteration": i, "beta": round(beta, 4), "dataset": len(d.dataset),
              "learner_step_fraction": mix["learner"] / max(1, mix["learner"] + mix["expert"])}
    if mix.get("scored") and mix["scored"] == mix["rollouts"]:  # rollouts before 2026-11-29 kept none
        record.update(rollout_success=mix["success"] / mix["scored"], rollout_cut=mix["cut"] / mix["scored"])
    if d.state.extra.get("refilled"):
        record["refilled"] = d.state.extra["refilled"]  # rollouts flown to refill a lost dataset
    return record


def _follow(run: RunFolder, model: torch.nn.Module, optimizer: torch.optim.Optimizer, world: distributed.World,
            state: TrainState | None) -> TrainState:
    """Every rank at rank 0's saved state: rank 0 (`state` given) has saved it; the others read it; then all go on
    together (no rank reads while rank 0 may be writing)."""
    distributed.barrier(world)
    if state is None:
        state = run.load_state(model, optimizer)
    distributed.barrier(world)
    return state


def _make_pool(config: RunConfig, dataset: EpisodeStore, policy_dir: Path,
               executor_options: ExecutorOptions | None = None) -> Executor:
    """`dagger.workers` rollout workers (processes, also for one: training keeps its threads)."""
    return make_executor(executor_options, config.dagger.workers, _init_worker,
                         (config, str(dataset.root), str(policy_dir)))


def _mixture_counts(dataset: EpisodeStore, jobs: list) -> dict[str, int]:
    """The iteration's expert and learner steps, and of its rollouts how many succeeded and how many were cut."""
    counts = dict.fromkeys(("expert", "learner", "scored", "success", "cut"), 0) | {"rollouts": len(jobs)}
    for key, *_ in jobs:
        meta = dataset.read_meta(key)
        counts["expert"] += meta["expert_steps"]
        counts["learner"] += meta["learner_steps"]
        if "success" in meta:
            counts["scored"] += 1
            counts["success"] += bool(meta["success"])
            counts["cut"] += bool(meta["cut"])
    return counts


def _link(src: Path, dst: Path) -> None:
    if dst.exists():
        return
    try:
        os.link(src, dst)
    except OSError:  # another file system: copy
        shutil.copy2(src, dst)
