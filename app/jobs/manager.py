"""Evaluations and DAggerFM fine-tuning runs launched from the dashboard, each in its own process group.

    evaluation:  gsmn eval --system S --checkpoint C --env-ids ... --record DIR --progress FILE --json FILE
    run:         gsmn collect (the expert demonstrations DAggerFM's dataset starts from, when missing)
                 && gsmn train dagger --init C --data STORE --run DIR [--env-ids ...] (paper: Algorithm 1)

each with `--config FOLDER/config.json`: the configuration the job runs with, saved in its folder when it starts.

Both write machine-readable progress (the evaluation one JSON line per episode; the run its folder's log.jsonl,
state and progress.json), and one monitor thread in the server reads it and records it in the SQLite database
(`app.jobs.db`): status (queued, running, finished, failed, cancelled), progress, metrics so far, the checkpoint when
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

This module is what the API and the view call (`JobManager`): what an evaluation runs and how its folder reads, and
the checks and records around launching a run. The process groups themselves are `app.jobs.supervisor`'s, a run's
settings `app.jobs.settings`', a run's commands and folder `app.jobs.runs`', the recorded episodes, summaries and
comparisons `app.jobs.results`'.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import stat
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path

from app.jobs.analysis import Analyses
from app.jobs.db import FINISHED, Database, Evaluation, Run
from app.jobs.results import EpisodeRecorder, compare, evaluation_config, folder_config, summarize_rows
from app.jobs.runs import DAGGER_KINDS, run_command, run_complete, run_progress
from app.jobs.settings import RunSettings, run_config
from app.jobs.supervisor import Handle, Supervisor, alive
from app.live.commands import Forbidden, NotFound, RunnerError, TooLarge
from gsmn.analysis.intervention import FLAG_LABELS as INTERVENTION_LABELS
from gsmn.config import RunConfig

log = logging.getLogger("gsmn.dashboard")

MAX_ENVIRONMENTS = 5000
CORES = os.cpu_count() or 1  # a job's worker processes (and a run's torch threads), at most
CHECKPOINTS = Path(__file__).resolve().parents[2] / "checkpoints"  # the shipped evaluations are read from here
MAX_IMPORT_BYTES = 256 * 2**20  # a `gsmn eval --json` file of 750 episodes with trajectories is a few MB


# -- the manager --------------------------------------------------------------------------------------------------
class JobManager:
    """Launches, watches, cancels and records evaluations and runs under `data_dir`.

    `resolve_checkpoint(ref)` turns a checkpoint name or path (None: the default one) into a folder, or raises
    RunnerError. Listeners are called as `listener(kind, id)` on the monitor thread after each change."""

    def __init__(self, data_dir: Path | str, config: RunConfig,
                 resolve_checkpoint: Callable[[str | None], Path], max_runs: int = 1, max_evaluations: int = 1,
                 python: str = sys.executable, poll_seconds: float = 0.5, checkpoints_root: Path | str = CHECKPOINTS):
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
        self.episodes = EpisodeRecorder(self.db)
        self.analyses = Analyses(self.db, config, Path(checkpoints_root))  # slices, confusions, shipped evaluations
        self.supervisor = Supervisor(self.db, self.root, self._poll, self._notify, poll_seconds)
        self.recovered = self.supervisor.recover()
        self.supervisor.start()

    def describe(self) -> str:
        evals, runs = self.db.evaluations(), self.db.runs()
        return (f"{self.root} ({len(evals)} evaluations, {len(runs)} runs recorded"
                + (f"; re-attached to {self.recovered} running" if self.recovered else "") + ")")

    def close(self) -> None:
        """Stop watching. Running jobs keep running; the next server re-attaches to them."""
        self.supervisor.close()
        self.db.close()

    # -- evaluations ---------------------------------------------------------------------------------------------
    def start_evaluation(self, checkpoint: str | None = None, system: str | None = None, split: str | None = None,
                         episodes: int | None = None, env_ids: list[int] | None = None,
                         baseline_id: int | None = None, run_id: int | None = None, workers: int = 1,
                         mirror_ensemble: bool = False, intervention: str | None = None,
                         like: Evaluation | None = None) -> Evaluation:
        """Launch `gsmn eval` on a split (its first `episodes`), a list of ids, or the ids of `baseline_id`, in
        `workers` processes of one torch thread each; `mirror_ensemble` flies the model as a test-time mirror
        ensemble (`--mirror-ensemble`); `intervention` ("truth-goal", ...) flies a GSMN with that map intervention
        from the first step (`--intervene`): with `baseline_id` and that evaluation's failures as `env_ids`, the
        rescue of its failures (`rescue_failures`). It flies with the configuration of `like`, else of the baseline
        (a rerun draws its images as the evaluation it reruns did), else the server's."""
        if system == "oracle" and mirror_ensemble:
            raise RunnerError("the expert has no mirror ensemble: it is a learned model's option")
        if system == "oracle":
            ckpt = None
        else:
            ckpt = self.resolve_checkpoint(checkpoint)
            system = evaluation_system(system, checkpoint is not None, _checkpoint_kind(ckpt), ckpt)
        ids, label = self._evaluation_ids(split, episodes, env_ids, baseline_id)
        like = like or (self.db.evaluation(baseline_id) if baseline_id is not None else None)
        config = evaluation_config(like, self.config)
        if not 1 <= workers <= CORES:
            raise RunnerError(f"workers must be between 1 and {CORES} (this machine's cores), got {workers}")
        if mirror_ensemble:
            label += ", mirror ensemble"
        if intervention is not None:
            self._check_intervention(intervention, system, ckpt, mirror_ensemble)
            label += f", {INTERVENTION_LABELS[intervention]}"
        with self.supervisor.lock:
            self.supervisor.check_limit("evaluation", self.max_evaluations, "--max-evaluations")
            eid = self.db.add_evaluation(system=system, checkpoint=str(ckpt) if ckpt else None, env_ids=ids,
                                         label=label, baseline_id=baseline_id, run_id=run_id,
                                         mirror_ensemble=mirror_ensemble, intervention=intervention)
            folder = new_job_folder(self.root / "evaluations", eid)
            self.db.update_evaluation(eid, folder=str(folder))
            (folder / "config.json").write_text(config.to_json() + "\n")
            command = [self.python, "-m", "gsmn.cli", "eval", "--system", system,
                       *(["--checkpoint", str(ckpt)] if ckpt is not None else []),
                       "--env-ids", ",".join(map(str, ids)), "--workers", str(workers), "--threads", "1",
                       "--record", str(folder / "episodes"), "--progress", str(folder / "progress.jsonl"),
                       "--json", str(folder / "results.json"), "--config", str(folder / "config.json"),
                       *(["--mirror-ensemble"] if mirror_ensemble else []),
                       *(["--intervene", intervention] if intervention else [])]
            self.supervisor.launch("evaluation", eid, folder, command)
        return self.db.evaluation(eid)

    def _evaluation_ids(self, split: str | None, episodes: int | None, env_ids: list[int] | None,
                        baseline_id: int | None) -> tuple[list[int], str]:
        """The environments an evaluation flies, checked, and how its label names them."""
        from gsmn.world.spec import SPLITS, split_env_ids

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
        return ids, label

    def cancel_evaluation(self, evaluation_id: int) -> Evaluation:
        self.supervisor.cancel("evaluation", self.evaluation(evaluation_id))
        return self.evaluation(evaluation_id)

    @staticmethod
    def _check_intervention(flag: str, system: str, ckpt, mirror_ensemble: bool) -> None:
        from gsmn.analysis.intervention import FLAGS, InterventionError, codes_for

        if flag not in FLAGS:
            raise RunnerError(f"intervention must be one of {', '.join(FLAGS)}, not {flag!r}")
        if system not in ("gsmn", "gsmn-no-plan") or mirror_ensemble:
            raise RunnerError("a map intervention flies one GSMN, not the expert, a first-person model or an "
                              "ensemble")
        try:
            codes_for(ckpt)
        except InterventionError as e:
            raise RunnerError(str(e)) from e

    def rescue_failures(self, evaluation_id: int, intervention: str) -> Evaluation:
        """Fly an evaluation's failures again with a truth map intervention from the first step: how many it
        rescues, per attributed stage, is the Failures tab's rescue table (`gsmn analyze rescue` on the command
        line)."""
        e = self.evaluation(evaluation_id)
        if e.intervention is not None:
            raise RunnerError(f"evaluation {e.id} flew with an intervention already: rescue the failures of one "
                              "that flew with the model's own maps")
        failures = [r.env_id for r in self.db.episodes(e.id, failed_only=True)]
        if not failures:
            raise RunnerError(f"evaluation {e.id} has no failure to rescue")
        rescue = self.start_evaluation(e.checkpoint, e.system, env_ids=failures, baseline_id=e.id,
                                       intervention=intervention)
        self.db.update_evaluation(rescue.id, label=f"the {len(failures)} failures of #{e.id}, "
                                                   f"{INTERVENTION_LABELS[intervention]}")
        return self.db.evaluation(rescue.id)

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
        episodes' traces, i.e. it was run with --record). Both must be inside the data folder (relative paths are
        taken from it); the file must be a regular one of at most MAX_IMPORT_BYTES."""
        path = self.inside_data(path, "path")
        record_dir = self.inside_data(record_dir, "record_dir") if record_dir is not None else None
        data = read_regular_file(path, MAX_IMPORT_BYTES)
        if record_dir is not None and not record_dir.is_dir():
            raise NotFound(f"record_dir {record_dir} is not a folder")
        try:
            results = json.loads(data)
            episodes, system = results["episodes"], results["system"]
            config = RunConfig.from_dict(results["config"])
        except (ValueError, KeyError, TypeError) as e:
            raise RunnerError(f"{path} is not a `gsmn eval --json` file: {type(e).__name__}: {e}") from e
        ids = [int(ep["env_id"]) for ep in episodes]
        mirror, others = bool(results.get("mirror_ensemble", False)), results.get("ensemble_with") or []
        label = f"imported from {path.name}" + (", mirror ensemble" if mirror else "")
        if others:  # a replay flies the first checkpoint alone (mirrored if it was), so it need not reproduce
            label += f", with {len(others)} more checkpoint{'s' if len(others) > 1 else ''}"
        eid = self.db.add_evaluation(system=system, checkpoint=results.get("checkpoint"), env_ids=ids,
                                     label=label, source="import", status=FINISHED, mirror_ensemble=mirror)
        folder = new_job_folder(self.root / "evaluations", eid)  # its settings as read, for reruns to fly the same
        (folder / "config.json").write_text(config.to_json() + "\n")
        self.db.update_evaluation(eid, folder=str(folder))
        for position, ep in enumerate(episodes):
            self.episodes.record(eid, position, ep, config, results.get("checkpoint") if system != "oracle" else None,
                                 Path(record_dir) if record_dir else None)
        self.db.update_evaluation(eid, done=len(ids), summary=results.get("summary"), started=time.time(),
                                  finished=time.time())
        self._notify("evaluation", eid)
        return self.db.evaluation(eid)

    def inside_data(self, path: str | Path, what: str) -> Path:
        """`path` (relative: to the data folder) resolved, if it lies in the data folder; else Forbidden, without
        saying whether it exists."""
        try:
            resolved = (self.root / path).resolve()
        except (OSError, RuntimeError) as e:
            raise RunnerError(f"{what} {path} cannot be resolved: {e}") from e
        if not resolved.is_relative_to(self.root):
            raise Forbidden(f"{what} must be inside the data folder {self.root} (write `gsmn eval --json` and "
                            "--record there)")
        return resolved

    def compare(self, before_id: int, after_id: int) -> dict:
        """The episodes two evaluations share, side by side (before/after a fine-tuning run)."""
        return compare(self.db, self.evaluation(before_id), self.evaluation(after_id))

    # -- runs ----------------------------------------------------------------------------------------------------
    def _expert_store(self, name: str | None) -> Path | None:
        """`expert_data` as a folder inside the data folder (a path relative to it, or an absolute one inside it):
        the run cleans and links files in that store, so a request cannot point it anywhere else; the refusal is
        the same whether the folder exists or not."""
        if name is None:
            return None
        refused = RunnerError(f"expert_data {name!r} is not an episode store inside the data folder ({self.root}): "
                              "name one there (a folder `gsmn collect --out` made), or leave it out to collect one")
        if not name.strip():
            raise refused
        try:
            path = (self.root / name).resolve()  # an absolute name stays itself
            if not path.is_relative_to(self.root) or path == self.root or not path.is_dir():
                raise refused
        except (OSError, RuntimeError) as e:
            raise refused from e
        return path

    def start_run(self, settings: RunSettings, checkpoint: str | None = None, env_ids: list[int] | None = None,
                  evaluation_id: int | None = None) -> Run:
        """Launch DAggerFM from a checkpoint on the train split, on `env_ids`, or on the failures of
        `evaluation_id` (when env_ids is not given). The job's folder keeps the run's configuration (config.json),
        which both of its commands start from: the server's, or the evaluation's (its camera's look with it), which
        the run's before/after flies again."""
        source = self.evaluation(evaluation_id) if evaluation_id is not None else None
        config = run_config(evaluation_config(source, self.config), settings)
        init = self.resolve_checkpoint(checkpoint)
        kind = _checkpoint_kind(init)
        if kind not in DAGGER_KINDS:
            raise RunnerError(f"checkpoint {init} holds a {kind!r} model, which DAggerFM cannot train")
        if source is not None:
            if env_ids is None:
                env_ids = [e.env_id for e in self.db.episodes(source.id, failed_only=True)]
                if not env_ids:
                    raise RunnerError(f"evaluation {source.id} has no failures to train on")
        if env_ids is not None:
            env_ids = sorted({int(e) for e in env_ids})
            if not env_ids or env_ids[0] < 0 or len(env_ids) > MAX_ENVIRONMENTS:
                raise RunnerError(f"need 1 to {MAX_ENVIRONMENTS} non-negative environment ids")
        for name in ("workers", "threads"):
            if getattr(settings, name) > CORES:
                raise RunnerError(f"{name} must be at most {CORES} (this machine's cores), got "
                                  f"{getattr(settings, name)}")
        expert_data = self._expert_store(settings.expert_data)
        with self.supervisor.lock:
            self.supervisor.check_limit("run", self.max_runs, "--max-runs")
            rid = self.db.add_run(settings=settings.to_dict(), env_ids=env_ids, init_checkpoint=str(init),
                                  folder="", source_evaluation_id=evaluation_id)
            folder = new_job_folder(self.root / "runs", rid)
            self.db.update_run(rid, folder=str(folder))
            (folder / "config.json").write_text(config.to_json() + "\n")
            command = run_command(self.python, self.root, folder, config, settings, init, env_ids, expert_data)
            self.supervisor.launch("run", rid, folder, command)
        return self.db.run(rid)

    def cancel_run(self, run_id: int) -> Run:
        self.supervisor.cancel("run", self.run(run_id))
        return self.run(run_id)

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

    # -- resuming and watching ---------------------------------------------------------------------------------
    def _resume(self, kind: str, job_id: int):
        with self.supervisor.lock:  # checked and relaunched as one step: two requests at once cannot start it twice
            row = self.run(job_id) if kind == "run" else self.evaluation(job_id)
            folder, command = self.supervisor.resumable_command(kind, row)
            if kind == "run":
                self.supervisor.check_limit("run", self.max_runs, "--max-runs")
            else:
                self.supervisor.check_limit("evaluation", self.max_evaluations, "--max-evaluations")
                if "--resume" not in command:
                    command.append("--resume")
                # the resumed process writes the progress file anew, the kept episodes first: read it from the start
                (folder / "progress.jsonl").write_text("")
            self.supervisor.relaunch(kind, job_id, folder, command)
        return self.run(job_id) if kind == "run" else self.evaluation(job_id)

    def _poll(self, h: Handle) -> None:
        if h.kind == "evaluation":
            self._poll_evaluation(h)
        else:
            self._poll_run(h)

    def _poll_evaluation(self, h: Handle) -> None:
        running, rc = alive(h)
        row = self.db.evaluation(h.id)
        config = folder_config(h.folder, self.config)
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
                    self.episodes.record(h.id, row.env_ids.index(record["env_id"]), record, config, row.checkpoint,
                                         h.folder / "episodes")
                    self.db.update_evaluation(h.id, done=int(record["done"]))
                    changed = True
            h.offset += end
        if changed:
            self.db.update_evaluation(h.id, summary=summarize_rows([e.__dict__ for e in self.db.episodes(h.id)]))
            self._notify("evaluation", h.id)
        self.supervisor.escalate(h, running)
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
        self.supervisor.settle(h, rc, complete, extra)

    def _poll_run(self, h: Handle) -> None:
        running, rc = alive(h)
        row = self.db.run(h.id)
        progress, metrics = run_progress(h.folder, row)
        stamp = json.dumps([progress, len(metrics)], sort_keys=True)
        if stamp != h.last:
            h.last = stamp
            self.db.update_run(h.id, progress=progress, metrics=metrics)
            self._notify("run", h.id)
        self.supervisor.escalate(h, running)
        if running:
            return
        self.supervisor.settle(h, rc, run_complete(h.folder, row, metrics),
                               {"checkpoint": str(h.folder / "run" / "checkpoint"),
                                "progress": {**progress, "fraction": 1.0}})

    def _notify(self, kind: str, job_id: int) -> None:
        for listener in list(self.listeners):
            try:
                listener(kind, job_id)
            except Exception:  # noqa: BLE001 - a viewer bug must not stop the monitor
                log.error("job listener failed:\n%s", traceback.format_exc())


# -- job folders ---------------------------------------------------------------------------------------------------
def new_job_folder(parent: Path, job_id: int) -> Path:
    """A folder for a new job, never one that holds files already: a record started afresh beside old job folders
    numbers its jobs from 1 again, and must not write over what they saved."""
    folder, n = parent / f"{job_id:04d}", 0
    while folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        n += 1
        folder = parent / f"{job_id:04d}-{n}"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def read_regular_file(path: Path, limit: int) -> bytes:
    """The bytes of a regular file of at most `limit` bytes. Opened without blocking and checked before reading, so
    a FIFO, a device (/dev/zero) or a huge file never holds the request's thread or the server's memory."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as e:
        if e.errno in (errno.ENOENT, errno.ENOTDIR):
            raise NotFound(f"no file {path}") from e
        raise RunnerError(f"cannot read {path}: {e.strerror or e}") from e
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise RunnerError(f"{path} is not a regular file")
        if info.st_size > limit:
            raise TooLarge(f"{path} is {info.st_size / 2**20:.0f} MiB, more than the {limit / 2**20:.0f} MiB an "
                           "import takes")
        chunks, size = [], 0
        while chunk := os.read(fd, 1 << 20):
            size += len(chunk)
            if size > limit:  # grew while being read
                raise TooLarge(f"{path} is more than the {limit / 2**20:.0f} MiB an import takes")
            chunks.append(chunk)
        return b"".join(chunks)
    except OSError as e:
        raise RunnerError(f"cannot read {path}: {e.strerror or e}") from e
    finally:
        os.close(fd)


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
