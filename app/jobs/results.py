"""What an evaluation's episodes come to, as the dashboard records them: each episode's row (with its failure
attributed to a stage of the model's pipeline from its recorded maps, `gsmn.attribution`, and the success region's
steps and P(stop)), the evaluation's summary, and two evaluations side by side (before and after fine-tuning)."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

from app.jobs.analysis import facts_of
from app.jobs.db import FINISHED, Database, EpisodeRow, Evaluation
from app.live.commands import RunnerError
from gsmn.config import RunConfig
from gsmn.task.metrics import record_region_steps, region_stop_probability

log = logging.getLogger("gsmn.dashboard")


class EpisodeRecorder:
    """Writes evaluated episodes into the database, attributing failures with each checkpoint's heads (loaded
    once per checkpoint)."""

    def __init__(self, db: Database):
        self.db = db
        self._heads: dict[str, object] = {}

    def record(self, evaluation_id: int, position: int, record: dict, config: RunConfig,
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
        try:  # for the analysis view; derived, so a record that lacks what they need is analysed from its row later
            facts = facts_of(record, config, attribution)
        except (KeyError, ValueError, TypeError, IndexError) as e:
            log.debug("no facts for episode %d of evaluation %d yet: %s", env_id, evaluation_id, e)
        else:
            self.db.set_facts(evaluation_id, {env_id: facts})

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


def compare(db: Database, before: Evaluation, after: Evaluation) -> dict:
    """The episodes two evaluations share, side by side (before/after a fine-tuning run)."""
    a = {e.env_id: e for e in db.episodes(before.id)}
    b = {e.env_id: e for e in db.episodes(after.id)}
    rows = []
    for env_id in before.env_ids:
        if env_id in a and env_id in b:
            rows.append({"env_id": env_id, "instruction": a[env_id].instruction, "before": _brief(a[env_id]),
                         "after": _brief(b[env_id])})
    fixed = sum(1 for r in rows if not r["before"]["success"] and r["after"]["success"])
    broken = sum(1 for r in rows if r["before"]["success"] and not r["after"]["success"])
    return {"before": before.id, "after": after.id, "before_checkpoint": before.checkpoint,
            "after_checkpoint": after.checkpoint, "episodes": rows, "fixed": fixed, "broken": broken,
            "before_success": _rate(r["before"]["success"] for r in rows),
            "after_success": _rate(r["after"]["success"] for r in rows),
            "before_mean_distance": _mean(r["before"]["goal_distance"] for r in rows),
            "after_mean_distance": _mean(r["after"]["goal_distance"] for r in rows),
            "before_stages": _stage_counts(r["before"] for r in rows),
            "after_stages": _stage_counts(r["after"] for r in rows)}


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


def replay_policy(e: Evaluation) -> tuple[str, str | None]:
    """Who flies a replay of an evaluation's episode: the expert for the oracle, else its checkpoint (as a mirror
    ensemble if the evaluation flew one)."""
    if e.system == "oracle":
        return "expert", None
    if not e.checkpoint:
        raise RunnerError(f"evaluation {e.id} ({e.system}) names no checkpoint to fly again")
    return ("mirror" if e.mirror_ensemble else "model"), e.checkpoint


def replay_intervention(e: Evaluation):
    """The map intervention a replay of an evaluation's episode flies with: the evaluation's (a rescue's true map),
    or None."""
    if not e.intervention:
        return None
    from gsmn.analysis.intervention import intervention_from_flag

    return intervention_from_flag(e.intervention)


def same_checkpoint(a: str | None, b: str | None) -> bool:
    """Whether two recorded checkpoint paths name one folder."""
    if a is None or b is None:
        return a == b
    try:
        return Path(a).resolve() == Path(b).resolve()
    except (OSError, RuntimeError):
        return a == b


def before_for_run(db: Database, run, baseline: Evaluation) -> Evaluation | None:
    """The evaluation to put before a run's checkpoint: `baseline` when it flew the checkpoint the run started from,
    else a finished evaluation of that starting checkpoint on the same environments, flown the same way (plain or
    mirrored, with the same camera look; None: there is none yet, so before/after would credit the change of
    checkpoint, or of look, to the fine-tune)."""
    if same_checkpoint(baseline.checkpoint, run.init_checkpoint):
        return baseline
    camera = evaluation_camera(baseline)
    for e in reversed(db.evaluations((FINISHED,))):
        if (same_checkpoint(e.checkpoint, run.init_checkpoint)
                and sorted(e.env_ids) == sorted(baseline.env_ids) and e.mirror_ensemble == baseline.mirror_ensemble
                and (camera is None or evaluation_camera(e) in (None, camera))):
            return e
    return None


def evaluation_config(e: Evaluation | None, default: RunConfig) -> RunConfig:
    """The configuration an evaluation flew with: its job folder's config.json, or `default` where it has none (an
    evaluation imported before imports kept theirs); `folder_config` refuses one it cannot read."""
    return folder_config(Path(e.folder), default) if e is not None and e.folder else default


def folder_config(folder: Path, default: RunConfig) -> RunConfig:
    """A job folder's config.json (one saved before a field existed reads as it ran, `gsmn.config.from_dict`), or
    `default` where it has none; one it cannot read is an error that names it (a rerun must not fly other
    settings than the evaluation it reruns)."""
    path = folder / "config.json"
    if not path.is_file():
        return default
    try:
        return RunConfig.from_dict(json.loads(path.read_text()))
    except (OSError, ValueError, TypeError) as e:  # ConfigError is a ValueError
        raise RunnerError(f"cannot read the settings in {path}: {e}") from e


def has_config(e: Evaluation) -> bool:
    """Whether the settings an evaluation flew with are known (a job folder with its config.json)."""
    return bool(e.folder) and (Path(e.folder) / "config.json").is_file()


def evaluation_camera(e: Evaluation):
    """The camera an evaluation flew with, or None where that is not known (or cannot be read)."""
    try:
        config = evaluation_config(e, None)
    except RunnerError:
        return None
    return config.camera if config is not None else None


def look_words(camera) -> str:
    """How a camera config draws its images, in words a user reads (the look a rerun must share to compare)."""
    if not camera.shadows:
        return "no shadows"
    return "baked shadows" if camera.baked_shadows else "MuJoCo's shadow passes"


RESCUE_ORDER = ("truth-semantic", "truth-relevance", "truth-goal")


def rescue_of(db: Database, e: Evaluation) -> dict:
    """The rescue table of `e`'s failures (`gsmn.analysis.rescue.rescue_table`), from the evaluations that flew them
    with a truth map intervention (`JobManager.rescue_failures`; the latest of each), with `evaluations` (their ids
    by intervention) and `running` (those still flying: status and progress)."""
    from gsmn.analysis.rescue import rescue_table

    latest = {x.intervention: x for x in db.evaluations() if x.baseline_id == e.id and x.intervention}
    stages = {r.env_id: r.stage for r in db.episodes(e.id, failed_only=True)}
    flown = {flag: [(r.env_id, r.success) for r in db.episodes(latest[flag].id)]
             for flag in RESCUE_ORDER if flag in latest}
    table = rescue_table(stages, flown)
    table["evaluations"] = {flag: x.id for flag, x in latest.items()}
    table["running"] = {flag: f"{x.status}, {x.done}/{x.total}" for flag, x in latest.items() if x.status != FINISHED}
    return table
