"""A fine-tuning run's settings: the presets the dashboard offers (tiny, small, paper), a preset with fields
overridden, and the run's configuration they make (which checks them)."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, fields, replace

from app.live.commands import RunnerError
from gsmn.config import ConfigError, RunConfig


@dataclass(frozen=True)
class RunSettings:
    """A DAggerFM fine-tuning run (gsmn.config.DaggerConfig and TrainConfig, plus where its data comes from)."""

    preset: str
    iterations: int  # DAggerFM iterations, one epoch each
    rollouts_per_iteration: int  # N_D
    dataset_size: int  # M
    beta0: float  # the expert acts with probability beta0 ** i in iteration i
    learning_rate: float
    horizon: int | None  # steps per rollout; None: the server's task.horizon
    batch_size: int
    workers: int  # rollout worker processes
    threads: int  # torch threads of the training process
    expert_data: str | None = None  # an expert episode store to start from; None: collect one in the data folder
    mirror: float = 0.0  # share of training episodes mirrored east-west (train.mirror; not in the paper)

    def to_dict(self) -> dict:
        return asdict(self)


MAX_ROLLOUTS = 2000  # iterations x N_D of a run launched from the dashboard
# expert episodes of the dev split a run launched from the dashboard validates on after every iteration, by preset
DEV_EPISODES = {"tiny": 2, "small": 8, "paper": 30}

RUN_PRESETS = {
    # a minute or two on a busy 2-core machine: 2 iterations of 2 short rollouts on a dataset of 4
    "tiny": RunSettings("tiny", iterations=2, rollouts_per_iteration=2, dataset_size=4, beta0=0.5,
                        learning_rate=1e-3, horizon=30, batch_size=2, workers=1, threads=1),
    # some tens of minutes: a first look at what fine-tuning on failures does
    "small": RunSettings("small", iterations=10, rollouts_per_iteration=8, dataset_size=40, beta0=0.92,
                         learning_rate=1e-3, horizon=None, batch_size=4, workers=1, threads=1),
    # the original's settings (gsmn.config.DaggerConfig)
    "paper": RunSettings("paper", iterations=150, rollouts_per_iteration=24, dataset_size=500, beta0=0.92,
                         learning_rate=1e-3, horizon=None, batch_size=4, workers=2, threads=1),
}


def run_settings(preset_name: str = "tiny", **overrides) -> RunSettings:
    """A preset with any fields overridden (None leaves the preset's value). Their values are checked where the
    configuration they become checks them: `run_config`."""
    if preset_name not in RUN_PRESETS:
        raise RunnerError(f"unknown run preset {preset_name!r}; choose from {', '.join(RUN_PRESETS)}")
    names = {f.name for f in fields(RunSettings)} - {"preset"}
    unknown = set(overrides) - names
    if unknown:
        raise RunnerError(f"unknown run setting(s): {', '.join(sorted(unknown))}")
    s = replace(RUN_PRESETS[preset_name], **{k: v for k, v in overrides.items() if v is not None})
    # what DaggerConfig checks (counts, N_D <= M, beta0, ...) it checks in run_config; this is the job's size
    if s.iterations * s.rollouts_per_iteration > MAX_ROLLOUTS:
        raise RunnerError(f"{s.iterations} iterations of {s.rollouts_per_iteration} rollouts are more than the "
                          f"dashboard launches (at most {MAX_ROLLOUTS} rollouts in all; the paper's 150 x 24 take "
                          "days on a few cores): run `gsmn train dagger` from a shell for that")
    return s


def run_config(config: RunConfig, s: RunSettings) -> RunConfig:
    """The server's configuration with a run's settings; the configuration checks them (DaggerConfig, TrainConfig,
    TaskConfig), and what it refuses is the request's error."""
    try:
        return replace(
            config,
            dagger=replace(config.dagger, iterations=s.iterations, rollouts_per_iteration=s.rollouts_per_iteration,
                           dataset_size=s.dataset_size, beta0=s.beta0, workers=s.workers),
            train=replace(config.train, learning_rate=s.learning_rate, batch_size=s.batch_size, threads=s.threads,
                          mirror=s.mirror),
            task=config.task if s.horizon is None else replace(config.task, horizon=s.horizon))
    except ConfigError as e:
        raise RunnerError(str(e)) from e


def expert_store_key(config: RunConfig) -> str:
    """Expert episodes depend on the world, drone, camera, task and expert settings: stores are kept apart by them."""
    parts = {k: config.to_dict()[k] for k in ("world", "drone", "camera", "task", "expert")}
    return hashlib.sha1(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:10]
