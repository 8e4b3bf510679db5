"""A training run's folder: resolved config, per-epoch log, resumable state and the resulting checkpoint.

    run_dir/
      config.json         the resolved RunConfig (a resumed run must match it, except that it may ask for more
                          epochs or DAgger iterations: that extends the run, optimizer state and all)
      log.jsonl           one JSON object per finished epoch (or DAgger iteration)
      state/              everything needed to resume: model weights (safetensors), optimizer state,
                          counters and running sums (JSON). Replaced atomically: a kill at any moment
                          leaves either the previous state or the new one, never half of one.
      checkpoint/         the latest model checkpoint (gsmn.model.checkpoint format)
      progress.json       where the run is now (phase, epoch or iteration, batch of batches, ...), rewritten
                          atomically at most once a second; monitors such as the dashboard read it, with the log
                          and the state, through `read_progress`

Optimizer state is saved as safetensors (`gsmn.model.checkpoint.save_optimizer_state`): never unpickled.
"""

from __future__ import annotations

import copy
import json
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from gsmn.config import RunConfig
from gsmn.model.checkpoint import (
    OPTIMIZER_FILE,
    checkpoint_iteration,
    cpu_weights,
    optimizer_file,
    read_optimizer_state,
    save_optimizer_state,
)


class RunError(ValueError):
    """A run folder cannot be used (e.g. resumed with a different configuration)."""


@dataclass
class TrainState:
    """Counters of a run. `batch` counts batches finished in the current epoch (or iteration)."""

    epoch: int = 0
    batch: int = 0
    step: int = 0
    sums: dict[str, float] = field(default_factory=dict)  # running sums of logged values this epoch
    counts: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0  # training time spent so far
    extra: dict[str, Any] = field(default_factory=dict)  # e.g. DAgger's dataset contents


EXTENDABLE = (("train", "epochs"), ("dagger", "iterations"))
# may change when a run resumes: what the next batches see, where and how they are computed and how often the state
# is saved, not what was saved
# (rollouts are seeded per rollout, not per worker, so the number of workers changes no flight)
ADJUSTABLE = (("train", "mirror"), ("train", "device"), ("train", "threads"), ("train", "prefetch"),
              ("train", "save_every_seconds"), ("dagger", "workers"))


def _normalised(saved: dict) -> dict:
    """A saved config.json with the defaults of fields added since it was written (an older run resumes)."""
    try:
        return json.loads(RunConfig.from_dict(saved).to_json())
    except (TypeError, ValueError):  # unknown fields or bad values: compare as written, and the comparison fails
        return saved


def _is_extension(saved: dict, new: dict) -> bool:
    """`new` equals `saved` but for a length in EXTENDABLE that did not shrink (and at least one that grew) and the
    settings in ADJUSTABLE."""
    trimmed_saved, trimmed_new = copy.deepcopy(saved), copy.deepcopy(new)
    for section, key in ADJUSTABLE:
        trimmed_saved.get(section, {}).pop(key, None)
        trimmed_new.get(section, {}).pop(key, None)
    if trimmed_saved == trimmed_new:
        return True
    grew = False
    for section, key in EXTENDABLE:
        old_value = trimmed_saved.get(section, {}).pop(key, None)
        new_value = trimmed_new.get(section, {}).pop(key, None)
        if old_value is None or new_value is None or new_value < old_value:
            return False
        grew |= new_value > old_value
    return grew and trimmed_saved == trimmed_new


class RunFolder:
    def __init__(self, root: Path | str):
        self.root = Path(root)
        self._progress_written = 0.0

    @property
    def state_dir(self) -> Path:
        return self.root / "state"

    @property
    def checkpoint_dir(self) -> Path:
        return self.root / "checkpoint"

    @property
    def log_path(self) -> Path:
        return self.root / "log.jsonl"

    def start(self, config: RunConfig) -> None:
        """Create the folder, or check that an existing one was made with the same configuration. The changes
        allowed are a longer run (more `train.epochs` or `dagger.iterations`, see EXTENDABLE) and the settings in
        ADJUSTABLE (the mirror augmentation, the device): the run continues from its saved state and the new
        configuration is recorded. Fields added to the configuration since the run was saved take their defaults."""
        self.root.mkdir(parents=True, exist_ok=True)
        path = self.root / "config.json"
        new = json.loads(config.to_json())
        if path.is_file():
            saved = _normalised(json.loads(path.read_text()))
            if saved == new:
                return
            if not _is_extension(saved, new):
                raise RunError(f"{self.root} holds a run with a different configuration; use a new run folder, "
                               "the same settings to resume it, or more epochs (iterations) to extend it")
        _write_atomic(path, config.to_json() + "\n")

    def has_state(self) -> bool:
        return (self.state_dir / "state.json").is_file() or (self.root / "state.old" / "state.json").is_file()

    def save_state(self, model: torch.nn.Module, optimizer: torch.optim.Optimizer, state: TrainState) -> None:
        tmp = self.root / "state.tmp"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        save_file(cpu_weights(model), tmp / "weights.safetensors")
        save_optimizer_state(tmp / OPTIMIZER_FILE, optimizer.state_dict())
        (tmp / "state.json").write_text(json.dumps(asdict(state)))
        old = self.root / "state.old"
        if old.exists():
            shutil.rmtree(old)
        if self.state_dir.exists():
            self.state_dir.rename(old)
        tmp.rename(self.state_dir)
        shutil.rmtree(old, ignore_errors=True)

    def load_state(self, model: torch.nn.Module, optimizer: torch.optim.Optimizer) -> TrainState:
        if not (self.state_dir / "state.json").is_file() and (self.root / "state.old" / "state.json").is_file():
            (self.root / "state.old").rename(self.state_dir)  # killed between the two renames
        model.load_state_dict(load_file(self.state_dir / "weights.safetensors"))  # copied onto the model's device
        optimizer.load_state_dict(read_optimizer_state(optimizer_file(self.state_dir)))
        return TrainState(**json.loads((self.state_dir / "state.json").read_text()))

    @property
    def progress_path(self) -> Path:
        return self.root / "progress.json"

    def write_progress(self, progress: dict, force: bool = False) -> None:
        """Record where the run is; throttled to once a second unless `force`."""
        now = time.monotonic()
        if force or now - self._progress_written >= 1.0:
            _write_atomic(self.progress_path, json.dumps({**progress, "time": time.time()}) + "\n")
            self._progress_written = now

    def read_progress(self) -> dict | None:
        try:
            return json.loads(self.progress_path.read_text())
        except (OSError, ValueError):
            return None

    def log(self, record: dict) -> None:
        with self.log_path.open("a") as f:
            f.write(json.dumps(record) + "\n")

    def read_log(self) -> list[dict]:
        if not self.log_path.is_file():
            return []
        return [json.loads(line) for line in self.log_path.read_text().splitlines() if line.strip()]

    def settle_log(self, epochs: int) -> None:
        """One record per saved epoch, as the run resumes with `epochs` saved. An epoch is logged after its state is
        saved, so a run killed between the two gets that record back from its checkpoint's meta.json (written
        before the state); records beyond `epochs` (a log written by older code before its state) are dropped,
        and those epochs logged again when they are trained again."""
        records = self.read_log()
        if len(records) == epochs - 1:
            try:
                meta = (self.checkpoint_dir / "meta.json").read_text()
                if checkpoint_iteration(meta) == epochs:
                    records.append(json.loads(meta)["metrics"])
            except (OSError, ValueError, AttributeError):
                pass  # no checkpoint of that epoch to take the record from: it stays one short
        elif len(records) > epochs:
            records = records[:epochs]
        else:
            return
        _write_atomic(self.log_path, "".join(json.dumps(r) + "\n" for r in records))


@dataclass(frozen=True)
class RunProgress:
    """Where a DAggerFM run is, as its folder tells a monitor (`read_progress`)."""

    phase: str  # "start", "discard", "collect", "train", "validate" or "done"
    done: int  # iterations finished (and logged)
    iterations: int  # iterations planned
    fraction: float  # of the whole run, in [0, 1]
    log: list[dict]  # one record per finished iteration (log.jsonl)
    iteration: int | None = None  # the iteration the last report is about (progress.json)
    rollouts: tuple[int, int] | None = None  # (done, of) this iteration's rollouts, while collecting
    beta: float | None = None  # the expert's share of this iteration's rollouts, while collecting
    batches: tuple[int, int] | None = None  # (done, of) this iteration's batches, while training
    loss: float | None = None  # the last batch's loss, while training


def read_progress(run_dir: Path | str, iterations: int | None = None) -> RunProgress | None:
    """Where the DAggerFM run in `run_dir` is, from its log, its last progress report and its state, or None before
    it has started (no config.json yet). `iterations`: those planned (default: the saved config's)."""
    run = RunFolder(run_dir)
    config_path = run.root / "config.json"
    if not config_path.is_file():
        return None
    if iterations is None:
        iterations = RunConfig.from_dict(json.loads(config_path.read_text())).dagger.iterations
    log = run.read_log()
    done = len(log)
    p = run.read_progress() or {}
    phase, within, extra = p.get("phase"), 0.0, {}
    if phase == "collect" and p.get("rollouts"):
        extra["rollouts"] = (int(p.get("done", 0)), int(p["rollouts"]))
        extra["beta"] = float(p.get("beta", 0.0))
        within = 0.5 * extra["rollouts"][0] / extra["rollouts"][1]
    elif phase == "train" and p.get("batches"):
        extra["batches"] = (int(p.get("batch", 0)), int(p["batches"]))
        extra["loss"] = float(p["loss"]) if p.get("loss") is not None else None
        within = 0.5 + 0.5 * extra["batches"][0] / extra["batches"][1]
    elif phase in ("validate", "done"):
        # The iteration's log line is written before the next progress report: once it is there, the "validate"
        # still in progress.json belongs to a finished iteration, already counted in `done`.
        stale = phase == "validate" and int(p.get("iteration", done + 1)) <= done
        within = 1.0 if phase == "done" else 0.0 if stale else 0.95
        extra["iteration"] = int(p.get("iteration", done))
    else:  # no report yet in this iteration: the phase the saved state is in
        try:
            state = json.loads((run.state_dir / "state.json").read_text())
        except (OSError, ValueError):
            state = {}
        phase = (state.get("extra") or {}).get("phase", "start")
    if done >= iterations:
        phase, within = "done", 0.0
    fraction = min(1.0, (done + within) / iterations)
    return RunProgress(phase=phase or "start", done=done, iterations=iterations, fraction=round(fraction, 4), log=log,
                       **extra)


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)
