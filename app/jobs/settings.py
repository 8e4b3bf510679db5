"""A fine-tuning run's settings: the presets the dashboard offers (tiny, small, paper: `gsmn.config.FINE_TUNE_PRESETS`,
which hold their numbers), a preset with fields overridden, and the run's configuration they make (which checks
them)."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, fields, replace

from app.live.commands import RunnerError
from gsmn.config import FINE_TUNE_PRESETS, ConfigError, FineTunePreset, RunConfig


@dataclass(frozen=True)
class RunSettings:
    """A DAggerFM fine-tuning run (gsmn.config.DaggerConfig and TrainConfig, plus where its data comes from); the
    record keeps it as its `to_dict()`."""

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
    mirror: float  # share of training episodes mirrored east-west (train.mirror; not in the paper)
    expert_data: str | None = None  # an expert episode store to start from; None: collect one in the data folder

    def to_dict(self) -> dict:
        return asdict(self)


# the settings that are configuration fields, by section, each named as its field (horizon is task.horizon, when given)
CONFIG_FIELDS = {"dagger": ("iterations", "rollouts_per_iteration", "dataset_size", "beta0", "workers"),
                 "train": ("learning_rate", "batch_size", "threads", "mirror")}


def preset_settings(name: str, p: FineTunePreset) -> RunSettings:
    """A fine-tuning preset of the configuration as a run's settings."""
    return RunSettings(name, horizon=p.horizon, **{f: getattr(getattr(p, section), f)
                                                   for section, names in CONFIG_FIELDS.items() for f in names})


MAX_ROLLOUTS = 2000  # iterations x N_D of a run launched from the dashboard
RUN_PRESETS = {name: preset_settings(name, p) for name, p in FINE_TUNE_PRESETS.items()}
# expert episodes of the dev split a run launched from the dashboard validates on after every iteration, by preset
DEV_EPISODES = {name: p.dev_episodes for name, p in FINE_TUNE_PRESETS.items()}
_PAPER = f"{RUN_PRESETS['paper'].iterations} x {RUN_PRESETS['paper'].rollouts_per_iteration}"


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
                          f"dashboard launches (at most {MAX_ROLLOUTS} rollouts in all; the paper's {_PAPER} take "
                          "days on a few cores): run `gsmn train dagger` from a shell for that")
    return s


def run_config(config: RunConfig, s: RunSettings) -> RunConfig:
    """The server's configuration with a run's settings; the configuration checks them (DaggerConfig, TrainConfig,
    TaskConfig), and what it refuses is the request's error."""
    try:
        sections = {section: replace(getattr(config, section), **{f: getattr(s, f) for f in names})
                    for section, names in CONFIG_FIELDS.items()}
        return replace(config, **sections,
                       task=config.task if s.horizon is None else replace(config.task, horizon=s.horizon))
    except ConfigError as e:
        raise RunnerError(str(e)) from e


def expert_store_key(config: RunConfig) -> str:
    """Expert episodes depend on the world, drone, camera, task and expert settings: stores are kept apart by them."""
    parts = {k: config.to_dict()[k] for k in ("world", "drone", "camera", "task", "expert")}
    return hashlib.sha1(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:10]
