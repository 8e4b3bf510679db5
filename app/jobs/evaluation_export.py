"""An evaluation's results as a file to take away (the Failures tab's Download, `GET /api/evaluations/{id}/export`):
CSV, one row per episode that says what flew it, or JSON, the evaluation with its summary and its episodes.

Each row names its environment's split, and the JSON counts them, so that figures on test or dev environments are
not mistaken for training ones (or the reverse); an evaluation still flying, cancelled or failed says so, with how
many of its episodes it holds.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections import Counter
from datetime import UTC, datetime

from app.jobs.db import Database, EpisodeRow, Evaluation
from gsmn.attribution import STAGE_TITLES
from gsmn.world.spec import split_of

FORMATS = {"csv": "text/csv", "json": "application/json"}
COLUMNS = ("evaluation_id", "position", "env_id", "split", "system", "checkpoint", "mirror_ensemble", "instruction",
           "landmark", "side", "ambiguous", "success", "landmark_success", "goal_distance_m", "steps", "stopped",
           "final_x", "final_y", "attributed_to", "stage", "reason", "region_steps", "region_stop_p")


def finite(value):
    """NaN and infinities are not JSON (nor useful in a spreadsheet): None instead, also inside lists and dicts (the
    API's job models read their figures through it too)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite(v) for v in value]
    return value


def episode_record(e: Evaluation, r: EpisodeRow) -> dict:
    """One episode as a row of the export: what flew it, where, how it ended and why it failed."""
    return {"evaluation_id": e.id, "position": r.position, "env_id": r.env_id, "split": split_of(r.env_id),
            "system": e.system, "checkpoint": e.checkpoint or "", "mirror_ensemble": e.mirror_ensemble,
            "instruction": r.instruction, "landmark": r.landmark, "side": r.side, "ambiguous": r.ambiguous,
            "success": r.success, "landmark_success": r.landmark_success, "goal_distance_m": finite(r.goal_distance),
            "steps": r.steps, "stopped": r.stopped, "final_x": r.final_x, "final_y": r.final_y,
            "attributed_to": STAGE_TITLES.get(r.stage, r.stage or ""), "stage": r.stage or "",
            "reason": (r.attribution or {}).get("reason", ""),
            "region_steps": None if r.region_steps is None else len(r.region_steps),
            "region_stop_p": finite(r.region_stop_p)}


def _time(t: float | None) -> str | None:
    return None if t is None else datetime.fromtimestamp(t, UTC).isoformat(timespec="seconds")


def evaluation_record(db: Database, e: Evaluation) -> dict:
    """The evaluation, its summary and its episodes in the order flown."""
    rows = [episode_record(e, r) for r in db.episodes(e.id)]
    complete = e.status == "finished" and len(rows) == e.total
    return finite({
        "evaluation": {"id": e.id, "label": e.label, "status": e.status, "system": e.system,
                       "checkpoint": e.checkpoint, "mirror_ensemble": e.mirror_ensemble, "env_ids": e.env_ids,
                       "created": _time(e.created), "finished": _time(e.finished), "episodes_held": len(rows),
                       "episodes_asked": e.total},
        "note": None if complete else (f"incomplete: {e.status}, {len(rows)} of {e.total} episodes flown; "
                                       "the figures are of those only"),
        "splits": dict(Counter(split_of(env) for env in e.env_ids)),
        "summary": {"success": sum(r["success"] for r in rows) / len(rows) if rows else None,
                    "landmark_success": sum(r["landmark_success"] for r in rows) / len(rows) if rows else None,
                    "mean_goal_distance_m": (sum(r["goal_distance_m"] or 0.0 for r in rows) / len(rows)
                                             if rows else None),
                    "failures_by_stage": dict(Counter(r["stage"] for r in rows if not r["success"] and r["stage"]))},
        "episodes": rows})


def export_evaluation(db: Database, e: Evaluation, fmt: str) -> bytes:
    """The evaluation as `fmt` (csv or json) bytes; ValueError for another format."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown format {fmt!r}; choose from {', '.join(FORMATS)}")
    record = evaluation_record(db, e)
    if fmt == "json":
        return (json.dumps(record, indent=1) + "\n").encode()
    out = io.StringIO()
    writer = csv.DictWriter(out, COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in record["episodes"]:
        writer.writerow({k: "" if v is None else v for k, v in row.items()})
    return out.getvalue().encode()


def export_name(e: Evaluation, fmt: str) -> str:
    return f"evaluation-{e.id}.{fmt}"
