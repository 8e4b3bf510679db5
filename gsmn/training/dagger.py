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
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from gsmn.config import RunConfig
from gsmn.executor import Executor, ExecutorOptions, make_executor, open_shared, shared_key
from gsmn.model.checkpoint import load_policy, read_checkpoint_kind, save_checkpoint, with_model_of
from gsmn.model.policy import MirrorEnsemble
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
    torch.set_num_threads(1)
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
    torch.set_num_threads(config.train.threads)
    kind = read_checkpoint_kind(init)  # first: a folder that is no checkpoint gets the clearest message
    config = with_model_of(config, init)
    dc, seed = config.dagger, config.train.seed
    world = distributed.init(config.train.device)
    run = RunFolder(run_dir)
    if world.main:
        run.start(config)
    distributed.barrier(world)
    config = on_rank_device(config, world)
    check_batch_size(config, world)
    dataset = EpisodeStore(run.root / "dataset")
    if world.main:
        model, vocabulary, optimizer, state = start_or_resume(run, kind, config, init, init_optimizer)
        state = TrainState(epoch=0, extra={"phase": "start"}) if state is None else state
        run.trim_log(state.epoch)
    else:  # the weights, Adam and counters come from rank 0's saved state (`_follow`)
        model, vocabulary, optimizer = make_model_and_optimizer(kind, config, init)
    expert_keys = expert_store.keys()
    if env_ids is None:
        env_ids = sorted({expert_store.read_meta(k).get("env_id", -1) for k in expert_keys} - {-1})
    if not env_ids:
        raise ValueError("no environments to roll out in: give env_ids or an expert store with env ids")
    # D holds M episodes from the start on (each iteration drops N_D and adds N_D); a run resumed without its
    # dataset (a new machine: the run's state restored, its episodes gone) refills it before the next iteration
    expected = min(dc.dataset_size, len(expert_keys)) if expert_keys else dc.dataset_size

    if world.main and state.extra["phase"] == "start":  # D ~ D*, M episodes (hard links: no copy of the data)
        chosen = _rng(seed, 0).choice(len(expert_keys), size=min(dc.dataset_size, len(expert_keys)), replace=False)
        for i in sorted(chosen):
            _link(expert_store.path(expert_keys[i]), dataset.path(expert_keys[i]))
        state.extra = {"phase": "discard"}
        run.save_state(model, optimizer, state)
    if world.size > 1:
        state = _follow(run, model, optimizer, world, state if world.main else None)

    pool = None
    try:
        while state.epoch < dc.iterations:
            i = state.epoch + 1  # iteration index, from 1
            beta = beta_schedule(dc.beta0, i)
            if world.main and state.extra["phase"] == "discard" and len(dataset) < expected:  # lost (a new machine)
                missing = expected - len(dataset)
                rng = _rng(seed, i, 1)
                jobs = [(f"refill_{i:04d}_{k:03d}_env_{e:06d}", int(e), i, beta, int(rng.integers(2**31)))
                        for k, e in enumerate(rng.choice(env_ids, size=missing, replace=True))]
                log(f"iteration {i}: the dataset holds {len(dataset)} of its {expected} episodes; refilling it with "
                    f"{missing} rollouts of the current mixture policy (beta {beta:.4g}), labelled by the expert")
                state.extra = {"phase": "refill", "jobs": jobs}
                run.save_state(model, optimizer, state)
            if world.main and state.extra["phase"] == "refill":
                save_checkpoint(run.root / "policy", model, config, vocabulary, meta={"iteration": i})
                todo = [tuple(j) for j in state.extra["jobs"] if j[0] not in dataset]
                if todo:
                    pool = pool or _make_pool(config, dataset, run.root / "policy", executor_options)
                    shared = pool.share(run.root / "policy")  # the weights once per phase, not with each rollout
                    for k, _ in enumerate(pool.map(_rollout_one, todo, shared), start=1):
                        _report(run, on_progress, {"phase": "collect", "iteration": i, "iterations": dc.iterations,
                                                   "beta": round(beta, 4), "rollouts": len(todo), "done": k})
                state.extra = {"phase": "discard", "refilled": len(state.extra["jobs"])}
                run.save_state(model, optimizer, state)
            if world.main and state.extra["phase"] == "discard":
                refilled = state.extra.get("refilled", 0)
                keys = dataset.keys()
                rng = _rng(seed, i)
                drop = [keys[j] for j in rng.choice(len(keys), size=min(dc.rollouts_per_iteration, len(keys)),
                                                     replace=False)]
                new_envs = [int(e) for e in rng.choice(env_ids, size=dc.rollouts_per_iteration, replace=True)]
                jobs = [(f"dagger_{i:04d}_{k:03d}_env_{e:06d}", e, i, beta, int(rng.integers(2**31)))
                        for k, e in enumerate(new_envs)]
                state.extra = {"phase": "collect", "drop": drop, "jobs": jobs, "refilled": refilled}
                run.save_state(model, optimizer, state)
            if world.main and state.extra["phase"] == "collect":
                for key in state.extra["drop"]:
                    dataset.delete(key)
                save_checkpoint(run.root / "policy", model, config, vocabulary, meta={"iteration": i})
                todo = [tuple(j) for j in state.extra["jobs"] if j[0] not in dataset]
                n_jobs = len(state.extra["jobs"])
                collect = {"phase": "collect", "iteration": i, "iterations": dc.iterations, "beta": round(beta, 4),
                           "rollouts": n_jobs}
                _report(run, on_progress, {**collect, "done": n_jobs - len(todo)}, force=True)
                if todo:
                    pool = pool or _make_pool(config, dataset, run.root / "policy", executor_options)
                    shared = pool.share(run.root / "policy")
                    for k, _ in enumerate(pool.map(_rollout_one, todo, shared), start=1):
                        _report(run, on_progress, {**collect, "done": n_jobs - len(todo) + k})
                state.extra = {"phase": "train", "mix": _mixture_counts(dataset, state.extra["jobs"]),
                               "refilled": state.extra.get("refilled", 0)}
                run.save_state(model, optimizer, state)
            if world.size > 1:  # the other ranks wait while rank 0 collects, then train from its saved state
                state = _follow(run, model, optimizer, world, state if world.main else None)
            if state.extra["phase"] == "train":
                if not run_epoch(run, model, optimizer, vocabulary, config, dataset, dataset.keys(), state, i,
                                 stop_after, on_progress, {"iteration": i, "iterations": dc.iterations}, world):
                    return run.checkpoint_dir
                if world.main:
                    _report(run, on_progress, {"phase": "validate", "iteration": i, "iterations": dc.iterations},
                            force=True)
                mix = state.extra["mix"]
                record = {"iteration": i, "beta": round(beta, 4), "dataset": len(dataset),
                          "learner_step_fraction": mix["learner"] / max(1, mix["learner"] + mix["expert"])}
                if mix.get("scored") and mix["scored"] == mix["rollouts"]:  # rollouts before 2026-11-29 kept none
                    record.update(rollout_success=mix["success"] / mix["scored"],
                                  rollout_cut=mix["cut"] / mix["scored"])
                if state.extra.get("refilled"):
                    record["refilled"] = state.extra["refilled"]  # rollouts flown to refill a lost dataset
                state.extra = {"phase": "discard"}
                finish_epoch(run, model, optimizer, vocabulary, config, state, record, dev_store, log, world)
                if on_iteration and world.main:
                    on_iteration(state)
                if distributed.agree(bool(world.main and stop_after and stop_after(state)), world,
                                     model_device(model)):
                    break
    finally:
        if pool is not None:  # stopped early: finish the rollouts in flight (written atomically), start no more
            pool.close()
    if state.epoch >= dc.iterations and world.main:
        _report(run, on_progress, {"phase": "done", "iteration": state.epoch, "iterations": dc.iterations},
                force=True)
    return run.checkpoint_dir


def _follow(run: RunFolder, model: torch.nn.Module, optimizer: torch.optim.Optimizer, world: distributed.World,
            state: TrainState | None) -> TrainState:
    """Every rank at rank 0's saved state: rank 0 (`state` given) has saved it; the others read it; then all go on
    together (no rank reads while rank 0 may be writing)."""
    distributed.barrier(world)
    if state is None:
        state = run.load_state(model, optimizer)
    distributed.barrier(world)
    return state


def _report(run: RunFolder, on_progress: Progress | None, progress: dict, force: bool = False) -> None:
    run.write_progress(progress, force=force)
    if on_progress:
        on_progress(progress)


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
