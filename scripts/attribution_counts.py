"""Failure attribution over a whole `gsmn eval` run: each failed episode traced to the first stage the model got
wrong (gsmn/attribution.py), and the counts.

    gsmn eval --system gsmn --split test --episodes 500 --json runs/eval.json --record runs/eval_rec
    .venv/bin/python scripts/attribution_counts.py runs/eval.json runs/eval_rec [--checkpoint checkpoints/gsmn]

The checkpoint defaults to the one the evaluation names (or checkpoints/gsmn); its heads read the recorded maps.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from gsmn.attribution import (
    STAGE_TITLES,
    STAGES,
    Heads,
    attribute_record,
    load_trace,
    reported_stages,
    trace_path,
)
from gsmn.config import RunConfig
from gsmn.model.checkpoint import load_checkpoint

ROOT = Path(__file__).resolve().parents[1]


def stage_counts(results: dict, recordings: Path, checkpoint: Path | None = None) -> tuple[dict[str, int], int]:
    """Failures per attribution stage over an evaluation's episodes, and how many failures had no recording.

    The checkpoint defaults to the one the evaluation names (or checkpoints/gsmn)."""
    checkpoint = checkpoint or Path(results.get("checkpoint") or ROOT / "checkpoints" / "gsmn")
    model, *_ = load_checkpoint(checkpoint)
    heads = Heads.of(model)
    config = RunConfig.from_dict(results["config"])
    counts, missing = dict.fromkeys(STAGES, 0), 0
    for record in results["episodes"]:
        if record["success"]:
            continue
        path = trace_path(recordings, int(record["env_id"]))
        if not path.is_file():
            missing += 1
            continue
        counts[attribute_record(record, load_trace(path), heads, config).stage] += 1
    return counts, missing


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path, help="gsmn eval --json output")
    ap.add_argument("recordings", type=Path, help="the same evaluation's --record folder")
    ap.add_argument("--checkpoint", type=Path, default=None)
    args = ap.parse_args(argv)
    results = json.loads(args.results.read_text())
    counts, missing = stage_counts(results, args.recordings, args.checkpoint)
    failures = sum(1 for r in results["episodes"] if not r["success"])
    stopped_steps = [r["steps"] for r in results["episodes"] if r["stopped"]]
    print(f"{failures} failures of {len(results['episodes'])} episodes "
          f"({args.checkpoint or results.get('checkpoint') or 'checkpoints/gsmn'}):")
    for stage in reported_stages(counts):
        print(f"  {STAGE_TITLES[stage]:<15} {counts[stage]}")
    if missing:
        print(f"  no recording    {missing}", file=sys.stderr)
    if stopped_steps:
        print(f"stopped by itself in {len(stopped_steps)} episodes, after {sum(stopped_steps) / len(stopped_steps):.0f}"
              " steps on average")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
