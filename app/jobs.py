"""Evaluations and DAggerFM fine-tuning runs launched from the dashboard, each in its own process group.

    evaluation:  gsmn eval --system S --checkpoint C --env-ids ... --record DIR --progress FILE --json FILE
    run:         gsmn collect (the expert demonstrations DAggerFM's dataset starts from, when missing)
                 && gsmn train dagger --init C --data STORE --run DIR [--env-ids ...] (paper: Algorithm 1)

Both write machine-readable progress (the evaluation one JSON line per episode; the run its folder's log.jsonl,
state and progress.json), and one monitor thread in the server reads it and records it in the SQLite database
(`app.db`): status (queued, running, finished, failed, cancelled), progress, metrics so far, the checkpoint when
done. Each failed episode of an evaluation is attributed to a stage of the model's pipeline from its recorded maps
(`gsmn.attribution`).

Processes are started niced, in a new session (their own process group, so their worker processes go with them),
with their output in the job folder. Cancel sends SIGTERM to the group and SIGKILL 5 s later. A process that dies
is marked failed with the end of its output; the server goes on. The processes do not depend on the server: when
it stops they keep running, and on the next start the monitor re-attaches to each row left running whose process
is still alive and is that job's command, or settles it from what its folder holds (finished if the results are
complete, else failed). Runs write only into their own folder, so no outcome of a run touches another checkpoint.
At most `max_runs` runs and `max_evaluations` evaluations at a time (1 by default): a request over the limit is
refused with a message, so background jobs never starve the live view of more cores.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

from app.commands import Conflict, NotFound, RunnerError
from app.db import ACTIVE, CANCELLED, FAILED, FINISHED, QUEUED, RUNNING, Database, EpisodeRow, Evaluation, Run
from gsmn.config import ConfigError, RunConfig, leaf_fields, preset, with_overrides
from gsmn.task.metrics import record_region_steps, region_stop_probability

log = logging.getLogger("gsmn.dashboard")

KILL_AFTER = 5.0  # s between SIGTERM and SIGKILL when cancelling
NICE = ["nice", "-n", "10"]  # jobs run below the live view's priority
MAX_ENVIRONMENTS = 5000


# -- settings -----------------------------------------------------------------------------------------------------
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
    """A preset with any fields overridden (None leaves the preset's value)."""
    if preset_name not in RUN_PRESETS:
        raise RunnerError(f"unknown run preset {preset_name!r}; choose from {', '.join(RUN_PRESETS)}")
    names = {f.name for f in fields(RunSettings)} - {"preset"}
    unknown = set(overrides) - names
    if unknown:
        raise RunnerError(f"unknown run setting(s): {', '.join(sorted(unknown))}")
    s = replace(RUN_PRESETS[preset_name], **{k: v for k, v in overrides.items() if v is not None})
    for name in ("iterations", "rollouts_per_iteration", "dataset_size", "batch_size", "workers", "threads"):
        if getattr(s, name) < 1:
            raise RunnerError(f"{name} must be at least 1, got {getattr(s, name)}")
    if s.rollouts_per_iteration > s.dataset_size:
        raise RunnerError(f"N_D (rollouts_per_iteration, {s.rollouts_per_iteration}) cannot exceed M "
                          f"(dataset_size, {s.dataset_size})")
    if not 0 <= s.beta0 <= 1:
        raise RunnerError(f"beta0 must be in [0, 1], got {s.beta0}")
    if not 0 <= s.mirror <= 1:
        raise RunnerError(f"mirror (the share of episodes mirrored) must be in [0, 1], got {s.mirror}")
    if not s.learning_rate > 0:
        raise RunnerError(f"learning_rate must be positive, got {s.learning_rate}")
    if s.horizon is not None and s.horizon < 1:
        raise RunnerError(f"horizon must be at least 1, got {s.horizon}")
    return s


def config_args(config: RunConfig) -> list[str]:
    """Command-line flags that rebuild `config` from the paper preset (`gsmn <verb> ... <flags>`)."""
    base, args = preset("paper"), []
    for path, _, _ in leaf_fields(RunConfig):
        value, default = config, base
        for part in path.split("."):
            value, default = getattr(value, part), getattr(default, part)
        if value != default:
            args += ["--" + path.replace("_", "-"), str(value).lower() if isinstance(value, bool) else str(value)]
    return args


def run_config(config: RunConfig, s: RunSettings) -> RunConfig:
    """The server's configuration with a run's settings."""
    overrides = {"dagger.iterations": s.iterations, "dagger.rollouts_per_iteration": s.rollouts_per_iteration,
                 "dagger.dataset_size": s.dataset_size, "dagger.beta0": s.beta0, "dagger.workers": s.workers,
                 "train.learning_rate": s.learning_rate, "train.batch_size": s.batch_size, "train.threads": s.threads,
                 "train.mirror": s.mirror}
    if s.horizon is not None:
        overrides["task.horizon"] = s.horizon
    try:
        return with_overrides(config, {k: str(v) for k, v in overrides.items()})
    except ConfigError as e:
        raise RunnerError(str(e)) from e


def expert_store_key(config: RunConfig) -> str:
    """Expert episodes depend on the world, drone, camera, task and expert settings: stores are kept apart by them."""
    parts = {k: config.to_dict()[k] for k in ("world", "drone", "camera", "task", "expert")}
    return hashlib.sha1(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:10]


# -- processes ----------------------------------------------------------------------------------------------------
@dataclass
class _Handle:
    kind: str  # "evaluation" or "run"
    id: int
    folder: Path
    pid: int
    proc: subprocess.Popen | None  # None when re-attached after a restart (not our child)
    offset: int = 0  # bytes of the progress file read so far (evaluations)
    kill_at: float | None = None
    last: str = ""  # the last progress written to the database, to write only changes


def resumable(job: Evaluation | Run) -> bool:
    """What `JobManager.resume_evaluation` / `resume_run` accept: a cancelled or failed job with a command
    recorded (not an import)."""
    return job.status in (CANCELLED, FAILED) and bool(job.command)


def _alive(h: _Handle) -> tuple[bool, int | None]:
    """(running, exit code if known)."""
    if h.proc is not None:
        rc = h.proc.poll()
        return rc is None, rc
    return _pid_runs(h.pid, str(h.folder)), None


def _pid_runs(pid: int | None, needle: str) -> bool:
    """The process exists, is not a zombie, and its command line mentions `needle` (not a reused pid)."""
    if not pid:
        return False
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return False
    state = stat.rsplit(")", 1)[-1].split()[0]
    return state not in ("Z", "X") and needle in cmdline


def _signal_group(pid: int, sig: int) -> None:
    try:
        os.killpg(pid, sig)  # the job's process group: started with start_new_session, so pgid == pid
    except (ProcessLookupError, PermissionError):
        pass


def _tail(path: Path, lines: int = 12) -> str:
    try:
        data = path.read_bytes()[-20000:].decode(errors="replace")
    except OSError:
        return ""
    parts = [p.rstrip() for p in data.replace("\r", "\n").split("\n") if p.strip()]
    return "\n".join(parts[-lines:])


def _exit_reason(rc: int | None) -> str:
    if rc is None:
        return "its process ended while the server was not watching"
    if rc < 0:
        try:
            return f"its process was killed by {signal.Signals(-rc).name}"
        except ValueError:
            return f"its process was killed by signal {-rc}"
    return f"its process exited with status {rc}"


# -- the manager --------------------------------------------------------------------------------------------------
class JobManager:
    """Launches, watches, cancels and records evaluations and runs under `data_dir`.

    `resolve_checkpoint(ref)` turns a checkpoint name or path (None: the default one) into a folder, or raises
    RunnerError. Listeners are called as `listener(kind, id)` on the monitor thread after each change."""

    def __init__(self, data_dir: Path | str, config: RunConfig,
                 resolve_checkpoint: Callable[[str | None], Path], max_runs: int = 1, max_evaluations: int = 1,
                 python: str = sys.executable, poll_seconds: float = 0.5):
        if max_runs < 1 or max_evaluations < 1:
            raise ValueError("max_runs and max_evaluations must be at least 1")
        self.root = Path(data_dir).resolve()
        self.root.mkdir(parents=True, exist_ok=True)
        self.db = Database(self.root / "gsmn.sqlite")
        self.config = config
        self.resolve_checkpoint = resolve_checkpoint
        self.max_runs, self.max_evaluations = max_runs, max_evaluations
        self.python = python
        self.poll_seconds = poll_seconds
        self.listeners: list[Callable[[str, int], None]] = []
        self._handles: dict[tuple[str, int], _Handle] = {}
        self._lock = threading.RLock()
        self._heads: dict[str, object] = {}
        self._stop = threading.Event()
        self.recovered = self._recover()
        self.thread = threading.Thread(target=self._monitor, name="gsmn-jobs", daemon=True)
        self.thread.start()

    def describe(self) -> str:
        evals, runs = self.db.evaluations(), self.db.runs()
        return (f"{self.root} ({len(evals)} evaluations, {len(runs)} runs recorded"
                + (f"; re-attached to {self.recovered} running" if self.recovered else "") + ")")

    def close(self) -> None:
        """Stop watching. Running jobs keep running; the next server re-attaches to them."""
        self._stop.set()
        self.thread.join(timeout=5)
        self.db.close()

    # -- evaluations ---------------------------------------------------------------------------------------------
    def start_evaluation(self, checkpoint: str | None = None, system: str | None = None, split: str | None = None,
                         episodes: int | None = None, env_ids: list[int] | None = None,
                         baseline_id: int | None = None, run_id: int | None = None, workers: int = 1,
                         mirror_ensemble: bool = False) -> Evaluation:
        """Launch `gsmn eval` on a split (its first `episodes`), a list of ids, or the ids of `baseline_id`, in
        `workers` processes of one torch thread each; `mirror_ensemble` flies the model as a test-time mirror
        ensemble (`--mirror-ensemble`)."""
        from gsmn.world.spec import SPLITS, split_env_ids

        if system == "oracle" and mirror_ensemble:
            raise RunnerError("the expert has no mirror ensemble: it is a learned model's option")
        if system == "oracle":
            ckpt = None
        else:
            ckpt = self.resolve_checkpoint(checkpoint)
            system = evaluation_system(system, checkpoint is not None, _checkpoint_kind(ckpt), ckpt)
        baseline = None
        if baseline_id is not None:
            baseline = self.db.evaluation(baseline_id)
            if baseline is None:
                raise NotFound(f"no evaluation {baseline_id}")
        if env_ids is not None:
            ids = [int(e) for e in env_ids]
            label = f"{len(ids)} chosen environments"
        elif split is not None:
            if split not in SPLITS:
                raise RunnerError(f"unknown split {split!r}; choose from {', '.join(SPLITS)}")
            if episodes is not None and episodes < 1:
                raise RunnerError(f"episodes must be at least 1, got {episodes}")
            ids = split_env_ids(split, episodes or 750)
            label = f"{split}, first {len(ids)}"
        elif baseline is not None:
            ids = list(baseline.env_ids)
            label = f"rerun of #{baseline.id}"
        else:
            raise RunnerError("give a split (and episodes), env_ids, or a baseline evaluation to rerun")
        if not ids or min(ids) < 0 or len(ids) > MAX_ENVIRONMENTS:
            raise RunnerError(f"need 1 to {MAX_ENVIRONMENTS} non-negative environment ids, got {len(ids)}")
        if len(set(ids)) != len(ids):
            raise RunnerError("environment ids repeat")
        if not 1 <= workers <= 16:
            raise RunnerError(f"workers must be between 1 and 16, got {workers}")
        if mirror_ensemble:
            label += ", mirror ensemble"
        with self._lock:
            self._check_limit("evaluation", self.max_evaluations, "--max-evaluations")
            eid = self.db.add_evaluation(system=system, checkpoint=str(ckpt) if ckpt else None, env_ids=ids,
                                         label=label, baseline_id=baseline_id, run_id=run_id,
                                         mirror_ensemble=mirror_ensemble)
            folder = self.root / "evaluations" / f"{eid:04d}"
            folder.mkdir(parents=True, exist_ok=True)
            self.db.update_evaluation(eid, folder=str(folder))
            (folder / "config.json").write_text(self.config.to_json() + "\n")
            command = [self.python, "-m", "gsmn.cli", "eval", "--system", system,
                       *(["--checkpoint", str(ckpt)] if ckpt is not None else []),
                       "--env-ids", ",".join(map(str, ids)), "--workers", str(workers), "--threads", "1",
                       "--record", str(folder / "episodes"), "--progress", str(folder / "progress.jsonl"),
                       "--json", str(folder / "results.json"), *config_args(self.config),
                       *(["--mirror-ensemble"] if mirror_ensemble else [])]
            self._launch("evaluation", eid, folder, command)
        return self.db.evaluation(eid)

    def cancel_evaluation(self, evaluation_id: int) -> Evaluation:
        return self._cancel("evaluation", evaluation_id)

    def resume_evaluation(self, evaluation_id: int) -> Evaluation:
        """Fly the rest of a cancelled or failed evaluation, as the same evaluation in its own folder: its command
        again with `--resume`, so `gsmn eval` keeps the episodes it had finished (`results.json.partial.jsonl`) and
        flies only the others. `gsmn eval` itself refuses (and the evaluation fails, saying what differs) if the
        checkpoint's weights have changed since."""
        return self._resume("evaluation", evaluation_id)

    def evaluation(self, evaluation_id: int) -> Evaluation:
        e = self.db.evaluation(evaluation_id)
        if e is None:
            raise NotFound(f"no evaluation {evaluation_id}")
        return e

    def import_evaluation(self, path: str | Path, record_dir: str | Path | None = None) -> Evaluation:
        """Record a `gsmn eval --json` file as a finished evaluation (attributed when `record_dir` holds the
        episodes' traces, i.e. it was run with --record)."""
        path = Path(path)
        try:
            results = json.loads(path.read_text())
            episodes, system = results["episodes"], results["system"]
            config = RunConfig.from_dict(results["config"])
        except OSError as e:
            raise RunnerError(f"cannot read {path}: {e.strerror or e}") from e
        except (ValueError, KeyError, TypeError) as e:
            raise RunnerError(f"{path} is not a `gsmn eval --json` file: {type(e).__name__}: {e}") from e
        ids = [int(ep["env_id"]) for ep in episodes]
        mirror, others = bool(results.get("mirror_ensemble", False)), results.get("ensemble_with") or []
        label = f"imported from {path.name}" + (", mirror ensemble" if mirror else "")
        if others:  # a replay flies the first checkpoint alone (mirrored if it was), so it need not reproduce
            label += f", with {len(others)} more checkpoint{'s' if len(others) > 1 else ''}"
        eid = self.db.add_evaluation(system=system, checkpoint=results.get("checkpoint"), env_ids=ids,
                                     label=label, source="import", status=FINISHED, mirror_ensemble=mirror)
        for position, ep in enumerate(episodes):
            self._record_episode(eid, position, ep, config, results.get("checkpoint") if system != "oracle" else None,
                                 Path(record_dir) if record_dir else None)
        self.db.update_evaluation(eid, done=len(ids), summary=results.get("summary"), started=time.time(),
                                  finished=time.time())
        self._notify("evaluation", eid)
        return self.db.evaluation(eid)

    def compare(self, before_id: int, after_id: int) -> dict:
        """The episodes two evaluations share, side by side (before/after a fine-tuning run)."""
        before, after = self.evaluation(before_id), self.evaluation(after_id)
        a = {e.env_id: e for e in self.db.episodes(before.id)}
        b = {e.env_id: e for e in self.db.episodes(after.id)}
        rows = []
        for env_id in before.env_ids:
            if env_id in a and env_id in b:
                rows.append({"env_id": env_id, "instruction": a[env_id].instruction, "before": _brief(a[env_id]),
                             "after": _brief(b[env_id])})
        fixed = sum(1 for r in rows if not r["before"]["success"] and r["after"]["success"])
        broken = sum(1 for r in rows if r["before"]["success"] and not r["after"]["success"])
        return {"before": before.id, "after": after.id, "episodes": rows, "fixed": fixed, "broken": broken,
                "before_success": _rate(r["before"]["success"] for r in rows),
                "after_success": _rate(r["after"]["success"] for r in rows),
                "before_mean_distance": _mean(r["before"]["goal_distance"] for r in rows),
                "after_mean_distance": _mean(r["after"]["goal_distance"] for r in rows),
                "before_stages": _stage_counts(r["before"] for r in rows),
                "after_stages": _stage_counts(r["after"] for r in rows)}

    # -- runs ----------------------------------------------------------------------------------------------------
    def start_run(self, settings: RunSettings, checkpoint: str | None = None, env_ids: list[int] | None = None,
                  evaluation_id: int | None = None) -> Run:
        """Launch DAggerFM from a checkpoint on the train split, on `env_ids`, or on the failures of
        `evaluation_id` (when env_ids is not given)."""
        init = self.resolve_checkpoint(checkpoint)
        kind = _checkpoint_kind(init)
        if kind not in ("gsmn", "gsmn-no-plan", "gs-fpv", "gs-fpv-mem"):
            raise RunnerError(f"checkpoint {init} holds a {kind!r} model, which DAggerFM cannot train")
        if evaluation_id is not None:
            source = self.evaluation(evaluation_id)
            if env_ids is None:
                env_ids = [e.env_id for e in self.db.episodes(source.id, failed_only=True)]
                if not env_ids:
                    raise RunnerError(f"evaluation {source.id} has no failures to train on")
        if env_ids is not None:
            env_ids = sorted({int(e) for e in env_ids})
            if not env_ids or env_ids[0] < 0 or len(env_ids) > MAX_ENVIRONMENTS:
                raise RunnerError(f"need 1 to {MAX_ENVIRONMENTS} non-negative environment ids")
        if settings.expert_data is not None and not Path(settings.expert_data).is_dir():
            raise RunnerError(f"expert_data {settings.expert_data} is not an episode store folder")
        config = run_config(self.config, settings)
        with self._lock:
            self._check_limit("run", self.max_runs, "--max-runs")
            rid = self.db.add_run(settings=settings.to_dict(), env_ids=env_ids, init_checkpoint=str(init),
                                  folder="", source_evaluation_id=evaluation_id)
            folder = self.root / "runs" / f"{rid:04d}"
            folder.mkdir(parents=True, exist_ok=True)
            self.db.update_run(rid, folder=str(folder))
            # the expert demonstrations the dataset starts from: a store named in the settings; else those of the
            # chosen environments, in the run's folder; else the train split's, shared by runs with the same settings
            if settings.expert_data:
                store = Path(settings.expert_data).resolve()  # the job runs in the repository, not our cwd
            elif env_ids is not None:
                store = folder / "expert"
            else:
                store = self.root / "expert" / expert_store_key(config)
            flags = config_args(config)
            parts = []
            if settings.expert_data is None:
                from gsmn.world.spec import split_env_ids

                demos = env_ids if env_ids is not None else split_env_ids("train", settings.dataset_size)
                parts.append(shlex.join([self.python, "-m", "gsmn.cli", "collect", "--out", str(store), "--env-ids",
                                         ",".join(map(str, demos)), "--workers", str(settings.workers), *flags]))
            dagger = [self.python, "-m", "gsmn.cli", "train", "dagger", "--init", str(init), "--data", str(store),
                      "--run", str(folder / "run"), *flags]
            if env_ids is not None:
                dagger += ["--env-ids", ",".join(map(str, env_ids))]
            parts.append("exec " + shlex.join(dagger))
            self._launch("run", rid, folder, ["sh", "-c", " && ".join(parts)])
        return self.db.run(rid)

    def cancel_run(self, run_id: int) -> Run:
        return self._cancel("run", run_id)

    def resume_run(self, run_id: int) -> Run:
        """Continue a cancelled or failed run from what its folder saved: its command again, as the same run (the
        collection skips the demonstrations it has, `gsmn train dagger` resumes from the run's state)."""
        return self._resume("run", run_id)

    def run(self, run_id: int) -> Run:
        r = self.db.run(run_id)
        if r is None:
            raise NotFound(f"no run {run_id}")
        return r

    def checkpoints(self) -> dict[str, Path]:
        """The checkpoints of finished runs, by name ("run-3")."""
        return {f"run-{r.id}": Path(r.checkpoint) for r in self.db.runs((FINISHED,))
                if r.checkpoint and (Path(r.checkpoint) / "meta.json").is_file()}

    # -- launching and cancelling --------------------------------------------------------------------------------
    def _check_limit(self, kind: str, limit: int, flag: str) -> None:
        active = [h for h in self._handles.values() if h.kind == kind]
        if len(active) >= limit:
            ids = ", ".join(str(h.id) for h in active)
            what = "fine-tuning run" if kind == "run" else "evaluation"
            raise Conflict(f"{limit} {what}{'s' if limit > 1 else ''} already running ({kind} {ids}): this machine "
                           f"runs at most {limit} at a time so that the live view keeps its share of the cores. Wait "
                           f"for it, or cancel it (DELETE /api/{kind}s/{active[0].id}); `gsmn serve {flag}` "
                           f"raises the limit.")

    def _launch(self, kind: str, job_id: int, folder: Path, command: list[str]) -> None:
        update = self.db.update_run if kind == "run" else self.db.update_evaluation
        if shutil.which("nice"):
            command = [*NICE, *command]
        out = (folder / "output.log").open("ab")
        try:
            proc = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    start_new_session=True, cwd=str(Path(__file__).resolve().parents[1]),
                                    env={**os.environ, "PYTHONUNBUFFERED": "1"})
        except OSError as e:
            update(job_id, status=FAILED, error=f"could not start: {e}", finished=time.time())
            raise RunnerError(f"could not start the {kind}: {e}") from e
        finally:
            out.close()
        update(job_id, status=RUNNING, pid=proc.pid, command=command, started=time.time())
        self._handles[(kind, job_id)] = _Handle(kind, job_id, folder, proc.pid, proc)
        self._notify(kind, job_id)

    def _cancel(self, kind: str, job_id: int):
        row = self.run(job_id) if kind == "run" else self.evaluation(job_id)
        update = self.db.update_run if kind == "run" else self.db.update_evaluation
        with self._lock:
            h = self._handles.get((kind, job_id))
            if row.status not in ACTIVE:
                raise Conflict(f"{kind} {job_id} is {row.status}: nothing to cancel")
            update(job_id, cancel_requested=True)
            if h is None:  # never started
                update(job_id, status=CANCELLED, finished=time.time())
            elif h.kill_at is None:
                _signal_group(h.pid, signal.SIGTERM)
                h.kill_at = time.monotonic() + KILL_AFTER
        self._notify(kind, job_id)
        return self.run(job_id) if kind == "run" else self.evaluation(job_id)

    def _resume(self, kind: str, job_id: int):
        update = self.db.update_run if kind == "run" else self.db.update_evaluation
        with self._lock:  # checked and relaunched as one step: two requests at once cannot start it twice
            row = self.run(job_id) if kind == "run" else self.evaluation(job_id)
            if row.status not in (CANCELLED, FAILED):
                raise Conflict(f"{kind} {job_id} is {row.status}: only a cancelled or failed one resumes")
            if not resumable(row) or not row.folder:
                raise Conflict(f"{kind} {job_id} has no command recorded (imported, or it never started): "
                               "nothing to resume")
            folder = Path(row.folder)
            if not folder.is_dir():
                raise Conflict(f"{kind} {job_id}'s folder {folder} is gone: start it again instead")
            command = list(row.command)
            if command[:len(NICE)] == NICE:
                command = command[len(NICE):]  # _launch adds it again
            if kind == "run":
                self._check_limit("run", self.max_runs, "--max-runs")
            else:
                self._check_limit("evaluation", self.max_evaluations, "--max-evaluations")
                if "--resume" not in command:
                    command.append("--resume")
                # the resumed process writes the progress file anew, the kept episodes first: read it from the start
                (folder / "progress.jsonl").write_text("")
            update(job_id, status=QUEUED, cancel_requested=False, error=None, finished=None)
            self._launch(kind, job_id, folder, command)
        return self.run(job_id) if kind == "run" else self.evaluation(job_id)

    # -- restart -------------------------------------------------------------------------------------------------
    def _recover(self) -> int:
        """Re-attach to the jobs a previous server left running; the monitor settles those whose process is gone."""
        attached = 0
        for kind, rows in (("evaluation", self.db.evaluations(ACTIVE)), ("run", self.db.runs(ACTIVE))):
            for row in rows:
                folder = Path(row.folder) if row.folder else self.root
                if row.status == QUEUED and not row.pid:
                    update = self.db.update_run if kind == "run" else self.db.update_evaluation
                    update(row.id, status=FAILED, error="the server stopped before it started", finished=time.time())
                    continue
                h = _Handle(kind, row.id, folder, row.pid or 0, None)
                alive = _pid_runs(row.pid, str(folder))
                if row.cancel_requested and alive:  # cancelled just before the restart: finish the job
                    _signal_group(h.pid, signal.SIGTERM)
                    h.kill_at = time.monotonic() + KILL_AFTER
                self._handles[(kind, row.id)] = h
                attached += alive
        return attached

    # -- the monitor ---------------------------------------------------------------------------------------------
    def _monitor(self) -> None:
        while not self._stop.wait(self.poll_seconds):
            for h in list(self._handles.values()):
                try:
                    with self._lock:
                        if h.kind == "evaluation":
                            self._poll_evaluation(h)
                        else:
                            self._poll_run(h)
                except Exception:  # noqa: BLE001 - one bad job must not stop watching the others
                    log.error("watching %s %d failed:\n%s", h.kind, h.id, traceback.format_exc())

    def _escalate(self, h: _Handle, running: bool) -> None:
        """SIGKILL a cancelled job that outlived its SIGTERM by KILL_AFTER (and again every second)."""
        if running and h.kill_at is not None and time.monotonic() >= h.kill_at:
            _signal_group(h.pid, signal.SIGKILL)
            h.kill_at = time.monotonic() + 1.0

    def _settle(self, h: _Handle, rc: int | None, complete: bool, update: Callable, extra: dict) -> None:
        row = self.db.run(h.id) if h.kind == "run" else self.db.evaluation(h.id)
        if row.cancel_requested:
            values = {"status": CANCELLED, "error": "cancelled"}
        elif complete and (rc == 0 or rc is None):
            values = {"status": FINISHED, **extra}
        else:
            tail = _tail(h.folder / "output.log")
            error = _exit_reason(rc) + (f"; its output ends:\n{tail}" if tail else "")
            values = {"status": FAILED, "error": error}
        _signal_group(h.pid, signal.SIGKILL)  # leftovers of the group (e.g. worker processes), if any
        update(h.id, finished=time.time(), **values)
        del self._handles[(h.kind, h.id)]
        self._notify(h.kind, h.id)

    def _poll_evaluation(self, h: _Handle) -> None:
        running, rc = _alive(h)
        row = self.db.evaluation(h.id)
        config = _folder_config(h.folder, self.config)
        progress = h.folder / "progress.jsonl"
        changed = False
        if progress.is_file():
            with progress.open("rb") as f:
                f.seek(h.offset)
                data = f.read()
            end = data.rfind(b"\n") + 1
            for line in data[:end].splitlines():
                if line.strip():
                    record = json.loads(line)
                    self._record_episode(h.id, row.env_ids.index(record["env_id"]), record, config, row.checkpoint,
                                         h.folder / "episodes")
                    self.db.update_evaluation(h.id, done=int(record["done"]))
                    changed = True
            h.offset += end
        if changed:
            self.db.update_evaluation(h.id, summary=summarize_rows([e.__dict__ for e in self.db.episodes(h.id)]))
            self._notify("evaluation", h.id)
        self._escalate(h, running)
        if running:
            return
        results = h.folder / "results.json"
        extra = {}
        complete = results.is_file()
        if complete:
            try:
                extra["summary"] = json.loads(results.read_text())["summary"]
            except (OSError, ValueError, KeyError):
                complete = False
        self._settle(h, rc, complete, self.db.update_evaluation, extra)

    def _poll_run(self, h: _Handle) -> None:
        running, rc = _alive(h)
        row = self.db.run(h.id)
        progress, metrics = run_progress(h.folder, row)
        stamp = json.dumps([progress, len(metrics)], sort_keys=True)
        if stamp != h.last:
            h.last = stamp
            self.db.update_run(h.id, progress=progress, metrics=metrics)
            self._notify("run", h.id)
        self._escalate(h, running)
        if running:
            return
        checkpoint = h.folder / "run" / "checkpoint"
        complete = len(metrics) >= row.settings["iterations"] and _loads(checkpoint)
        self._settle(h, rc, complete, self.db.update_run, {"checkpoint": str(checkpoint),
                                                            "progress": {**progress, "fraction": 1.0}})

    # -- episodes and their attribution --------------------------------------------------------------------------
    def _record_episode(self, evaluation_id: int, position: int, record: dict, config: RunConfig,
                        checkpoint: str | None, record_dir: Path | None) -> None:
        from gsmn.attribution import load_trace, trace_path

        env_id = int(record["env_id"])
        recording = trace_path(record_dir, env_id) if record_dir is not None else None
        trace = None
        if recording is not None and recording.is_file():
            try:
                trace = load_trace(recording)
            except (OSError, ValueError, KeyError) as e:
                log.warning("cannot read %s: %s", recording, e)
        else:
            recording = None
        attribution = self._attribute(record, config, checkpoint, trace) if trace is not None and checkpoint else None
        region = region_steps_of(record, config.task.success_radius)
        stop_p = region_stop_p_of(record, region, trace.stop_probability if trace is not None else None)
        self.db.add_episode(EpisodeRow(
            evaluation_id=evaluation_id, position=position, env_id=env_id, instruction=record["instruction"],
            landmark=record["noun_phrase"], side=record["side"], ambiguous=bool(record["ambiguous"]),
            success=bool(record["success"]), landmark_success=bool(record["landmark_success"]),
            goal_distance=float(record["goal_distance"]), steps=int(record["steps"]), stopped=bool(record["stopped"]),
            final_x=float(record["final_x"]), final_y=float(record["final_y"]),
            stage=attribution.get("stage") if attribution else None, attribution=attribution,
            recording=str(recording) if recording else None, region_steps=region, region_stop_p=stop_p))

    def _attribute(self, record: dict, config: RunConfig, checkpoint: str, trace) -> dict | None:
        from gsmn.attribution import attribute_record

        heads = self._heads_of(checkpoint)
        if heads is None:
            return None
        return attribute_record(record, trace, heads, config).to_dict()

    def _heads_of(self, checkpoint: str):
        if checkpoint not in self._heads:
            from gsmn.attribution import Heads
            from gsmn.model.checkpoint import CheckpointError, load_checkpoint

            try:
                model, *_ = load_checkpoint(checkpoint)
                self._heads[checkpoint] = Heads.of(model)
            except (CheckpointError, ValueError, OSError) as e:
                log.warning("no attribution for %s: %s", checkpoint, e)
                self._heads[checkpoint] = None
        return self._heads[checkpoint]

    def _notify(self, kind: str, job_id: int) -> None:
        for listener in list(self.listeners):
            try:
                listener(kind, job_id)
            except Exception:  # noqa: BLE001 - a viewer bug must not stop the monitor
                log.error("job listener failed:\n%s", traceback.format_exc())


def region_steps_of(record: dict, success_radius: float) -> list[int] | None:
    """The steps at which an evaluated episode was inside its success region: from a progress line (which carries
    them), from a `gsmn eval --json` record's trajectory, or None for an older progress line with neither."""
    if record.get("region_steps") is not None:
        return [int(i) for i in record["region_steps"]]
    if not record.get("trajectory"):
        return None
    return record_region_steps(record, success_radius)


def region_stop_p_of(record: dict, region: list[int] | None, recorded=None) -> float | None:
    """The highest P(stop) at the steps `region`: the one the policy acted on (an ensemble's mean), from a
    `gsmn eval --json` record or its progress line; else from the recording's per-step P(stop) `recorded` (for a
    mirror ensemble the unmirrored copy's), for files written before evaluations kept it; else None."""
    if not region:
        return None
    stop_p = region_stop_probability(record, region)
    if stop_p is None and record.get("region_stop_p") is not None:
        stop_p = float(record["region_stop_p"])
    if stop_p is None and recorded is not None and max(region) < len(recorded):
        stop_p = float(max(recorded[i] for i in region))
    return stop_p


# -- reading a run's folder ---------------------------------------------------------------------------------------
def run_progress(folder: Path, row: Run) -> tuple[dict, list[dict]]:
    """Where a run is (phase, iteration, overall fraction, a line for people) and its per-iteration log so far,
    from its folder: the expert store while collecting, then the run folder's log.jsonl, state and progress.json."""
    from gsmn.training.run import RunFolder

    iterations = int(row.settings["iterations"])
    run = RunFolder(folder / "run")
    metrics = run.read_log() if run.log_path.is_file() else []
    done = len(metrics)
    if not (run.root / "config.json").is_file():
        return {"phase": "expert data", "iteration": 0, "iterations": iterations, "fraction": 0.0,
                "text": "collecting the expert demonstrations the dataset starts from"}, metrics
    p = _read_json(run.root / "progress.json") or {}
    within, text = 0.0, f"iteration {min(done + 1, iterations)} of {iterations}"
    phase = p.get("phase")
    if phase == "collect" and p.get("rollouts"):
        within = 0.5 * p.get("done", 0) / p["rollouts"]
        text += f": rollouts {p.get('done', 0)}/{p['rollouts']} (beta {p.get('beta', 0):.2f})"
    elif phase == "train" and p.get("batches"):
        within = 0.5 + 0.5 * p.get("batch", 0) / p["batches"]
        text += f": training, batch {p.get('batch', 0)}/{p['batches']}"
        if p.get("loss") is not None:
            text += f", loss {p['loss']:.3f}"
    elif phase in ("validate", "done"):
        # The iteration's log line is written before the next progress report: once it is there, the "validate"
        # still in progress.json belongs to a finished iteration, already counted in `done`.
        stale = phase == "validate" and int(p.get("iteration", done + 1)) <= done
        within = 1.0 if phase == "done" else 0.0 if stale else 0.95
        text = f"iteration {p.get('iteration', done)} of {iterations}: {phase}"
    else:
        state = _read_json(run.state_dir / "state.json") or {}
        phase = (state.get("extra") or {}).get("phase", "start")
        text += f": {phase}"
    if done >= iterations:
        phase, within, text = "done", 0.0, f"{iterations} iterations done"
    fraction = min(1.0, (done + within) / iterations)
    out = {"phase": phase or "start", "iteration": done, "iterations": iterations, "fraction": round(fraction, 4),
           "text": text}
    if metrics:
        out["loss"] = metrics[-1].get("train", {}).get("loss")
    return out, metrics


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _folder_config(folder: Path, default: RunConfig) -> RunConfig:
    d = _read_json(folder / "config.json")
    return RunConfig.from_dict(d) if d else default


def evaluation_system(system: str | None, checkpoint_named: bool, kind: str, checkpoint: Path) -> str:
    """The system an evaluation flies with a checkpoint of `kind`: the one asked for, which must match it, or when
    none was asked for, the checkpoint's own kind. An explicit 'gsmn' with the server's default checkpoint (none
    named) also takes that checkpoint's kind."""
    if system is None or system == kind or (system == "gsmn" and not checkpoint_named):
        return kind
    raise RunnerError(f"checkpoint {checkpoint} holds a {kind!r} model, not {system!r}")


def _checkpoint_kind(folder: Path) -> str:
    from gsmn.model.checkpoint import CheckpointError, read_checkpoint_kind

    try:
        return read_checkpoint_kind(folder)
    except CheckpointError as e:
        raise RunnerError(str(e)) from e


def _loads(folder: Path) -> bool:
    from gsmn.model.checkpoint import CheckpointError, load_checkpoint

    try:
        load_checkpoint(folder)
        return True
    except (CheckpointError, OSError, ValueError):
        return False


def summarize_rows(rows: list[dict]) -> dict:
    """Success %, landmark success %, mean and median distance of episode rows (as gsmn.task.metrics.summarize,
    from the recorded outcomes)."""

    def one(rs: list[dict]) -> dict:
        n = len(rs)
        d = sorted(r["goal_distance"] for r in rs)
        median = (d[(n - 1) // 2] + d[n // 2]) / 2 if n else math.nan
        return {"count": n, "success": _rate(r["success"] for r in rs),
                "landmark_success": _rate(r["landmark_success"] for r in rs),
                "mean_distance": sum(d) / n if n else math.nan, "median_distance": median}

    out = one(rows)
    out["pruned"] = {**one([r for r in rows if not r["ambiguous"]]), "pruned": None}
    return out


def _rate(values) -> float:
    values = [bool(v) for v in values]
    return 100.0 * sum(values) / len(values) if values else math.nan


def _mean(values) -> float:
    values = list(values)
    return sum(values) / len(values) if values else math.nan


def _brief(e: EpisodeRow) -> dict:
    return {"success": e.success, "landmark_success": e.landmark_success, "goal_distance": e.goal_distance,
            "steps": e.steps, "stopped": e.stopped, "stage": e.stage}


def _stage_counts(briefs) -> dict[str, int]:
    from gsmn.attribution import STAGES

    counts = dict.fromkeys(STAGES, 0)
    for b in briefs:
        if not b["success"] and b["stage"] in counts:
            counts[b["stage"]] += 1
    return counts
