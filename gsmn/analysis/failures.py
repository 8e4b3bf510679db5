"""Failure attribution over a whole `gsmn eval` run (`gsmn attribute`): each failed episode traced to the first stage
the model got wrong (gsmn/attribution.py), and the counts; the control failures also by how the drone missed the
goal peak; how many episodes stopped by itself and how many ended outside the field.

    gsmn eval --system gsmn --split test --episodes 500 --json runs/eval.json --record runs/eval_rec
    gsmn attribute runs/eval.json runs/eval_rec [--checkpoint checkpoints/gsmn]

The checkpoint defaults to the one the evaluation names (or checkpoints/gsmn); its heads read the recorded maps.
"""

from __future__ import annotations

import sys
from pathlib import Path

from gsmn.attribution import (
    STAGE_TITLES,
    Attribution,
    Heads,
    attribute_record,
    count_stages,
    load_trace,
    reported_stages,
    trace_path,
)
from gsmn.config import RunConfig
from gsmn.evaluation import checkpoint_path
from gsmn.model.checkpoint import load_checkpoint
from gsmn.task.metrics import landmark_success
from gsmn.world.spec import on_field, world_for_env


def failed_attributions(results: dict, recordings: Path, checkpoint: Path | None = None) -> list[Attribution | None]:
    """The attribution of every failed episode of an evaluation (None where it has no recording).

    The checkpoint defaults to the one the evaluation names (or checkpoints/gsmn)."""
    checkpoint = checkpoint or checkpoint_path("gsmn", results.get("checkpoint"))
    model, *_ = load_checkpoint(checkpoint)
    heads = Heads.of(model)
    config = RunConfig.from_dict(results["config"])
    out = []
    for record in results["episodes"]:
        if record["success"]:
            continue
        path = trace_path(recordings, int(record["env_id"]))
        out.append(attribute_record(record, load_trace(path), heads, config) if path.is_file() else None)
    return out


def stage_counts(results: dict, recordings: Path, checkpoint: Path | None = None) -> tuple[dict[str, int], int]:
    """Failures per attribution stage over an evaluation's episodes, and how many failures had no recording."""
    return _tally(failed_attributions(results, recordings, checkpoint))


def _tally(found: list[Attribution | None]) -> tuple[dict[str, int], int]:
    return count_stages(found), sum(a is None for a in found)


def ambiguous_counts(results: dict, attributions: list[Attribution | None]) -> dict[str, int]:
    """How many of each stage's failures had an ambiguous instruction (its noun phrase names several landmarks of
    the world, so only one of them is the goal and the instruction cannot say which)."""
    failed = [r for r in results["episodes"] if not r["success"]]
    out: dict[str, int] = {}
    for record, a in zip(failed, attributions, strict=True):
        if a is not None and a.stage is not None and record.get("ambiguous"):
            out[a.stage] = out.get(a.stage, 0) + 1
    return out


def ambiguous_endings(results: dict) -> dict[str, int]:
    """Where the episodes with an ambiguous instruction ended: within 6 m of the named landmark, of another landmark
    of the same name (the instruction fitted it as well), or of neither."""
    world_config = RunConfig.from_dict(results["config"]).world
    out = {"the named one": 0, "another of that name": 0, "neither": 0}
    for r in results["episodes"]:
        if not r.get("ambiguous"):
            continue
        final = (r["final_x"], r["final_y"])
        if landmark_success(final, (r["landmark_x"], r["landmark_y"])):
            out["the named one"] += 1
            continue
        world = world_for_env(int(r["env_id"]), world_config)
        named = world.landmarks[int(r["landmark_index"])]
        near_other = any(landmark_success(final, (lm.x, lm.y))
                         for lm in world.landmarks_named(r["noun_phrase"]) if lm is not named)
        out["another of that name" if near_other else "neither"] += 1
    return out


def control_misses(attributions: list[Attribution | None]) -> dict[str, int]:
    """The control failures by how the drone missed the goal peak: stopped short, overshot, beside, never stopped
    ("direction unknown" only for episodes recorded without their final heading)."""
    kinds = {"ahead": "stopped short", "behind": "overshot", "left": "beside", "right": "beside",
             None: "direction unknown"}
    out = dict.fromkeys(("stopped short", "overshot", "beside", "never stopped"), 0)
    for a in attributions:
        if a is not None and a.stage == "control":
            kind = "never stopped" if not a.stopped else kinds[a.peak_bearing]
            out[kind] = out.get(kind, 0) + 1
    return out


def ended_outside(results: dict) -> int:
    """How many of an evaluation's episodes ended with the drone outside the field (world.field_size square)."""
    size = RunConfig.from_dict(results["config"]).world.field_size
    return sum(not on_field(r["final_x"], r["final_y"], size) for r in results["episodes"])


def print_report(results: dict, recordings: Path, checkpoint: Path | None = None) -> None:
    """The counts of an evaluation's failures by stage, and how its episodes ended, as `gsmn attribute` prints them
    (failures without a recording are counted on stderr)."""
    found = failed_attributions(results, recordings, checkpoint)
    counts, missing = _tally(found)
    failures = sum(1 for r in results["episodes"] if not r["success"])
    stopped_steps = [r["steps"] for r in results["episodes"] if r["stopped"]]
    print(f"{failures} failures of {len(results['episodes'])} episodes "
          f"({checkpoint or results.get('checkpoint') or 'checkpoints/gsmn'}):")
    ambiguous = ambiguous_counts(results, found)
    for stage in reported_stages(counts):
        title = STAGE_TITLES.get(stage, stage)
        print(f"  {title:<15} {counts[stage]}  ({ambiguous.get(stage, 0)} with an ambiguous instruction)")
        if stage == "control" and counts[stage]:
            for kind, n in control_misses(found).items():
                print(f"    {kind:<13} {n}")
    if missing:
        print(f"  no recording    {missing}", file=sys.stderr)
    if stopped_steps:
        print(f"stopped by itself in {len(stopped_steps)} episodes, after {sum(stopped_steps) / len(stopped_steps):.0f}"
              " steps on average")
    print(f"ended outside the field in {ended_outside(results)} episodes")
    endings = ambiguous_endings(results)
    if ambiguous := sum(endings.values()):
        succeeded = sum(bool(r["success"]) for r in results["episodes"] if r.get("ambiguous"))
        print(f"{ambiguous} ambiguous episodes ({succeeded} succeeded) ended near "
              + ", ".join(f"{where} {n}" for where, n in endings.items()))
