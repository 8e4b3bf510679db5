"""Evaluation: fly a system on many environments, in parallel worker processes, and summarise it as a row
of the paper's Table 1 (success %, landmark success %, mean and median distance to the goal; the pruned,
unambiguous subset in brackets).

Workers are separate processes started with "spawn" (a forked MuJoCo/EGL context is not safe), or Ray actors
(`gsmn.executor`); each holds its own environment and policy and flies whole episodes. Results come back in
the order of the ids.

With `record_dir`, a GSMN's final maps and per-step readings of each episode are written there
(`gsmn.attribution.ModelTrace`, one .npz per environment), for failure attribution and the dashboard.
"""

from __future__ import annotations

import json
import platform
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import gsmn
from gsmn.config import RunConfig
from gsmn.executor import ExecutorOptions, make_executor
from gsmn.task.baselines import (
    TRIVIAL_SYSTEMS,
    AverageAction,
    AvgForwardPolicy,
    ExpertPolicy,
    RandomLandmarkPolicy,
    RandomPointPolicy,
)
from gsmn.task.metrics import Summary, record_region_steps, region_stop_probability, summarize
from gsmn.task.rollout import EpisodeRecord, Policy, rollout, task_for_env
from gsmn.world.env import Env
from gsmn.world.spec import split_env_ids

if TYPE_CHECKING:
    from gsmn.analysis.intervention import Intervention

REPO_ROOT = Path(gsmn.__file__).resolve().parents[1]
AVG_FORWARD_PATH = REPO_ROOT / "checkpoints" / "avg_forward.json"
LEARNED_SYSTEMS = ("gsmn", "gsmn-no-plan", "gs-fpv", "gs-fpv-mem")
SYSTEMS = LEARNED_SYSTEMS + TRIVIAL_SYSTEMS
# A learned system's checkpoint when none is named: checkpoints/SYSTEM, except GSMN without J_plan, whose shipped
# model is Table 2's (`gsmn experiment table2`, docs/results.md).
DEFAULT_CHECKPOINTS = {"gsmn-no-plan": "table2/no-plan"}


def checkpoint_path(system: str, checkpoint: str | Path | None = None) -> Path | None:
    """Where `system` loads from: `checkpoint`, else its default (checkpoints/SYSTEM for a learned system, or its
    `DEFAULT_CHECKPOINTS` entry; checkpoints/avg_forward.json for avg-forward); None for systems without one."""
    if checkpoint:
        return Path(checkpoint)
    if system in LEARNED_SYSTEMS:
        return REPO_ROOT / "checkpoints" / DEFAULT_CHECKPOINTS.get(system, system)
    return AVG_FORWARD_PATH if system == "avg-forward" else None


def make_policy(system: str, config: RunConfig, checkpoint: str | Path | None = None,
                mirror_ensemble: bool = False, ensemble_with: Sequence[str | Path] = (),
                intervention: Intervention | None = None) -> Policy:
    """The policy of a system. Learned systems only: `ensemble_with` names more checkpoints of the same system
    that fly beside it as a test-time ensemble, and `mirror_ensemble` flies each model on the mirror image too
    (`gsmn.model.policy.Ensemble`); `intervention`: a GSMN flies every episode with that map intervention from its
    first step (`gsmn.analysis.intervention`)."""
    if intervention is not None:
        return _intervened_policy(system, config, checkpoint, mirror_ensemble or bool(ensemble_with), intervention)
    if (mirror_ensemble or ensemble_with) and system not in LEARNED_SYSTEMS:
        flag = "--mirror-ensemble" if mirror_ensemble else "--ensemble-with"
        raise ValueError(f"{flag} needs a learned system ({', '.join(LEARNED_SYSTEMS)}), not {system!r}")
    if system == "oracle":
        return ExpertPolicy(config)
    if system == "random-point":
        return RandomPointPolicy(config)
    if system == "random-landmark":
        return RandomLandmarkPolicy(config)
    if system == "avg-forward":
        return AvgForwardPolicy(AverageAction.load(checkpoint_path(system, checkpoint)))
    if system in LEARNED_SYSTEMS:
        from gsmn.model.checkpoint import load_policy

        folders = [checkpoint_path(system, checkpoint)]
        folders += [Path(c) for c in ensemble_with]
        policies = [load_policy(folder) for folder in folders]
        for folder, policy in zip(folders, policies, strict=True):
            if policy.model.kind != system:
                raise ValueError(f"{folder} holds a {policy.model.kind!r} model, not {system!r}")
            for part in ("world", "drone", "camera", "task", "model"):  # what flying it depends on
                if getattr(policy.config, part) != getattr(policies[0].config, part):
                    raise ValueError(f"{folder} has other {part} settings than {folders[0]}: an ensemble's models "
                                     "must share them")
        if mirror_ensemble or ensemble_with:
            from gsmn.model.policy import Ensemble, MirrorEnsemble

            return Ensemble(policies, mirror=mirror_ensemble) if ensemble_with else MirrorEnsemble(policies[0])
        return policies[0]
    raise ValueError(f"unknown system {system!r}; available: {', '.join(SYSTEMS)}")


def _intervened_policy(system: str, config: RunConfig, checkpoint: str | Path | None, ensemble: bool,
                       intervention: Intervention) -> Policy:
    from gsmn.analysis.intervention import InterventionError, InterventionMaker, check_model, codes_for

    if system not in ("gsmn", "gsmn-no-plan") or ensemble:
        raise InterventionError(f"a map intervention flies one GSMN (gsmn or gsmn-no-plan), not {system!r}"
                                + (" as an ensemble" if ensemble else ""))
    policy = make_policy(system, config, checkpoint)
    check_model(policy.model)
    codes = codes_for(checkpoint_path(system, checkpoint))
    policy.intervene(InterventionMaker(intervention, codes, policy.model.config.model.map_size,
                                       config.task.success_radius))
    return policy


def parse_env_ids(spec: str) -> list[int]:
    """'A:B' (A inclusive, B exclusive) or a comma-separated list '3,17,42'."""
    try:
        if ":" in spec:
            a, b = (int(s) for s in spec.split(":"))
            ids = list(range(a, b))
        else:
            ids = [int(s) for s in spec.split(",") if s.strip()]
    except ValueError as e:
        raise ValueError(f"--env-ids takes 'A:B' or '3,17,42', got {spec!r}") from e
    if not ids or min(ids) < 0:
        raise ValueError(f"--env-ids must name at least one non-negative id, got {spec!r}")
    return ids


def env_ids_for(split: str | None, episodes: int | None, env_ids: str | None) -> list[int]:
    if env_ids is not None:
        return parse_env_ids(env_ids)
    if split is None:
        raise ValueError("give --split or --env-ids")
    return split_env_ids(split, episodes or 750)


# -- workers ----------------------------------------------------------------------------------------
_worker: dict = {}


def _init_worker(system: str, config: RunConfig, checkpoint: str | None, render: bool | None,
                 threads: int | None = None, record_dir: str | None = None, mirror_ensemble: bool = False,
                 ensemble_with: Sequence[str] = (), intervention: Intervention | None = None) -> None:
    if threads is not None:
        from gsmn.model.runtime import set_torch_threads

        set_torch_threads(threads)
    _use(make_policy(system, config, checkpoint, mirror_ensemble, ensemble_with, intervention), config, render,
         record_dir)


def _use(policy: Policy, config: RunConfig, render: bool | None, record_dir: str | None = None) -> None:
    render = policy.needs_images if render is None else render
    if record_dir is not None and policy.name in ("gsmn", "gsmn-no-plan"):  # the models with world maps
        from gsmn.attribution import TraceRecorder

        policy = TraceRecorder(policy)
    _worker.update(config=config, policy=policy, env=Env(config, render=render), record_dir=record_dir)


def _run_one(env_id: int) -> EpisodeRecord:
    config: RunConfig = _worker["config"]
    policy = _worker["policy"]
    record = rollout(_worker["env"], policy, task_for_env(env_id, config), config.task.horizon,
                     success_radius=config.task.success_radius)
    if _worker.get("record_dir") is not None and hasattr(policy, "trace"):
        from gsmn.attribution import save_trace, trace_path

        save_trace(trace_path(_worker["record_dir"], env_id), policy.trace())
    return record


def evaluate(system: str, env_ids: Sequence[int], config: RunConfig, checkpoint: str | Path | None = None,
             workers: int = 1, on_episode: Callable[[EpisodeRecord], None] | None = None,
             render: bool | None = None, record_dir: str | Path | None = None,
             mirror_ensemble: bool = False, ensemble_with: Sequence[str | Path] = (),
             executor_options: ExecutorOptions | None = None, intervention: Intervention | None = None
             ) -> list[EpisodeRecord]:
    """Fly `system` on each environment id; records in the order of `env_ids`, on `workers` workers of the
    executor `executor_options` names (default: worker processes on this host; `gsmn.executor`). `render`
    forces the camera on or off (default: only for policies that look). `record_dir`: write each episode's
    ModelTrace there (GSMN only; other systems have no maps and write nothing). `mirror_ensemble`,
    `ensemble_with`, `intervention`: see `make_policy`."""
    checkpoint = str(checkpoint) if checkpoint is not None else None
    record_dir = str(record_dir) if record_dir is not None else None
    ensemble_with = [str(c) for c in ensemble_with]
    # fails here, clearly, before any worker starts
    policy = make_policy(system, config, checkpoint, mirror_ensemble, ensemble_with, intervention)
    records = []

    def in_process():  # one worker: this process, with the policy loaded above
        _use(policy, config, render, record_dir)
        return lambda: _worker.pop("env").close()

    executor = make_executor(executor_options, workers, _init_worker,
                             (system, config, checkpoint, render, 1, record_dir,  # a core each
                              mirror_ensemble, ensemble_with, intervention), in_process=in_process)
    try:
        for record in executor.map(_run_one, env_ids):
            records.append(record)
            if on_episode:
                on_episode(record)
    finally:  # stopped early (SIGTERM, Ctrl-C, an error): finish the episodes in flight, start no more
        executor.close()
    return records


# -- reporting --------------------------------------------------------------------------------------
TABLE_HEADER = f"{'system':18} {'success %':>17} {'landmark %':>17} {'mean dist (m)':>15} {'median dist (m)':>15}"


def table_row(system: str, s: Summary) -> str:
    """One row of Table 1; the pruned (unambiguous) figures in brackets."""
    p = s.pruned or s
    return (f"{system:18} {s.success:7.2f} ({p.success:6.2f}) {s.landmark_success:7.2f} ({p.landmark_success:6.2f}) "
            f"{s.mean_distance:6.2f} ({p.mean_distance:5.2f}) {s.median_distance:6.2f} ({p.median_distance:5.2f})")


def results_dict(system: str, checkpoint: str | None, records: list[EpisodeRecord], config: RunConfig,
                 seconds: float, workers: int, mirror_ensemble: bool = False,
                 ensemble_with: Sequence[str] = ()) -> dict:
    summary = summarize(records, config.task.success_radius)
    return {
        "system": system, "checkpoint": checkpoint, "mirror_ensemble": mirror_ensemble,
        "ensemble_with": [str(c) for c in ensemble_with],
        "env_ids": [r.env_id for r in records], "summary": summary.to_dict(), "seconds": round(seconds, 2),
        "workers": workers,
        "machine": platform.machine(), "config": config.to_dict(),
        "episodes": [r.to_dict() for r in records],
    }


def _checkpoint_bytes(path: str | None) -> dict[str, bytes] | None:
    """The bytes of the checkpoint files that decide what is evaluated: weights, config and vocabulary (not
    meta.json, nor an optimizer state or other files beside them)."""
    from gsmn.model.checkpoint import FILES

    folder = Path(path) if path else None
    if folder is None or not folder.is_dir():
        return None
    return {name: (folder / name).read_bytes() for name in FILES if name != "meta.json" and (folder / name).is_file()}


def checkpoint_fingerprint(system: str, checkpoint: str | None) -> str | None:
    """A SHA-256 over what decides how `system` flies from `checkpoint` (the default one where None): a learned
    system's weights, config and vocabulary, avg-forward's JSON; None for systems without one."""
    import hashlib

    path = checkpoint_path(system, checkpoint)
    if path is None:
        return None
    if system in LEARNED_SYSTEMS:
        files = _checkpoint_bytes(str(path)) or {}
    else:  # avg-forward's JSON
        files = {path.name: path.read_bytes()} if path.is_file() else {}
    digest = hashlib.sha256()
    for name in sorted(files):
        digest.update(name.encode() + b"\0" + hashlib.sha256(files[name]).digest())
    return digest.hexdigest()


class PartialResults:
    """The finished episodes of an evaluation that writes `--json F`, kept in `F.partial.jsonl` as they finish
    (one line of settings, then one full record a line, flushed at once), so that a run stopped before its end
    (Ctrl-C, SIGTERM, a machine going away) loses at most the episodes in flight: `gsmn eval ... --resume` with the
    same settings flies only the rest. The file is removed once F is written.

    `open(resume=False)` refuses to overwrite a partial file (saved work) and says how to go on; with `resume=True`
    it returns the records kept there after checking that the header (what `gsmn eval` puts there: the system, the
    environments, the checkpoint by a hash of its bytes, the settings, the ensemble) is the same. A last line cut
    short by a kill is dropped. The JSON's `seconds` are then the resumed run's only."""

    def __init__(self, json_path: str | Path):
        self.path = Path(str(json_path) + ".partial.jsonl")

    def open(self, header: dict, resume: bool) -> list[EpisodeRecord]:
        header = json.loads(json.dumps(header))  # as it reads back from the file (tuples become lists)
        kept: list[EpisodeRecord] = []
        if self.path.exists():
            lines = self.path.read_text().splitlines()
            if not resume:
                raise ValueError(f"{self.path} holds {max(len(lines) - 1, 0)} finished episode(s) of an earlier run "
                                 "that stopped before its end: pass --resume to fly only the rest, or remove the "
                                 "file to start again")
            try:
                old = _settings_as_read(json.loads(lines[0])) if lines else None
            except (ValueError, TypeError, AttributeError):  # not JSON, or settings this code cannot read
                old = None
            if old != header:
                differs = sorted(k for k in header if old is None or old.get(k) != header[k])
                raise ValueError(f"{self.path} was written by an evaluation with other settings ({', '.join(differs)}"
                                 "): it cannot be resumed with these; remove it to start again")
            for line in lines[1:]:
                try:
                    kept.append(EpisodeRecord.from_dict(json.loads(line)))
                except (json.JSONDecodeError, TypeError, KeyError):
                    continue  # the line being written when the run was stopped
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.write_text("".join(json.dumps(x) + "\n" for x in [header] + [r.to_dict() for r in kept]))
        tmp.replace(self.path)
        return kept

    def append(self, record: EpisodeRecord) -> None:
        with self.path.open("a") as f:
            f.write(json.dumps(record.to_dict()) + "\n")

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


def _settings_as_read(header: dict) -> dict:
    """A partial file's header with its settings as this code reads them: a field the file was written without
    takes the value it ran with (`gsmn.config.from_dict`), so an evaluation written before a field existed resumes
    under the settings it flew."""
    if isinstance(header.get("config"), dict):
        header = {**header, "config": json.loads(RunConfig.from_dict(header["config"]).to_json())}
    return header


def merge_results(parts: Sequence[dict]) -> dict:
    """One evaluation from several `results_dict`s of the same system, checkpoint and settings on disjoint
    environments (an evaluation run in pieces), with the summary recomputed over all episodes.

    Checkpoints named by different paths count as the same when their weights, config and vocabulary files are
    byte-identical. Raises ValueError for anything else, rather than mix results that are not comparable."""
    if not parts:
        raise ValueError("nothing to merge")
    first = parts[0]
    seen: set[int] = set()
    for part in parts:
        if part["system"] != first["system"]:
            raise ValueError(f"different systems: {first['system']} and {part['system']}")
        if part.get("mirror_ensemble", False) != first.get("mirror_ensemble", False):
            raise ValueError("one evaluation ran as a mirror ensemble, another did not")
        if part.get("ensemble_with", []) != first.get("ensemble_with", []):
            raise ValueError("the evaluations flew different ensembles")
        if RunConfig.from_dict(part["config"]) != RunConfig.from_dict(first["config"]):
            raise ValueError("the evaluations ran with different settings")
        if part["checkpoint"] != first["checkpoint"]:
            a, b = _checkpoint_bytes(first["checkpoint"]), _checkpoint_bytes(part["checkpoint"])
            if a is None or a != b:
                raise ValueError(f"different checkpoints: {first['checkpoint']} and {part['checkpoint']}")
        overlap = seen.intersection(part["env_ids"])
        if overlap:
            raise ValueError(f"environments evaluated twice: {sorted(overlap)[:5]}")
        seen.update(part["env_ids"])
    episodes = [e for part in parts for e in part["episodes"]]
    config = RunConfig.from_dict(first["config"])
    return {
        "system": first["system"], "checkpoint": first["checkpoint"],
        "mirror_ensemble": first.get("mirror_ensemble", False), "ensemble_with": first.get("ensemble_with", []),
        "env_ids": [e for part in parts for e in part["env_ids"]],
        "summary": summarize(episodes, config.task.success_radius).to_dict(),
        "seconds": round(sum(part["seconds"] for part in parts), 2),
        "workers": first["workers"], "machine": first["machine"], "config": first["config"],
        "parts": [{"checkpoint": p["checkpoint"], "episodes": len(p["env_ids"]), "seconds": p["seconds"]}
                  for p in parts],
        "episodes": episodes,
    }


def write_json(path: Path, results: dict) -> None:
    """Write atomically: a killed run never leaves half a file where a good one was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(results) + "\n")
    tmp.replace(path)



class ProgressLog:
    """One JSON line per finished episode (the record without its trajectory but with its final heading, the steps
    at which it was inside the success region, and how many are done of how many), flushed at once: what a
    monitor such as the dashboard reads while an evaluation runs."""

    def __init__(self, path: Path, total: int, success_radius: float = 6.0):
        self.path, self.total, self.done = Path(path), total, 0
        self.success_radius = success_radius
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text("")

    def write(self, record: EpisodeRecord) -> None:
        self.done += 1
        d = record.to_dict()
        line = {k: v for k, v in d.items() if k not in ("trajectory", "actions", "stop_probabilities",
                                                         "member_stop_probabilities")}
        line["final_yaw"] = record.trajectory[-1][3]  # for failure attribution (which way a control failure missed)
        line["region_steps"] = region = record_region_steps(d, self.success_radius)  # flew through it: STOP
        line["region_stop_p"] = region_stop_probability(d, region)
        with self.path.open("a") as f:
            f.write(json.dumps({"done": self.done, "total": self.total, **line}) + "\n")
