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

from gsmn.attribution import STAGE_TITLES, STAGES, Heads, attribute_record, load_trace, trace_path
from gsmn.config import RunConfig
from gsmn.model.checkpoint import load_checkpoint

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path, help="gsmn eval --json output")
    ap.add_argument("recordings", type=Path, help="the same evaluation's --record folder")
    ap.add_argument("--checkpoint", type=Path, default=None)
    args = ap.parse_args(argv)
    results = json.loads(args.results.read_text())
    checkpoint = args.checkpoint or Path(results.get("checkpoint") or ROOT / "checkpoints" / "gsmn")
    model, *_ = load_checkpoint(checkpoint)
    heads = Heads.of(model)
    config = RunConfig.from_dict(results["config"])
    counts, missing, failures, stopped_steps = dict.fromkeys(STAGES, 0), 0, 0, []
    for record in results["episodes"]:
        if record["stopped"]:
            stopped_steps.append(record["steps"])
        if record["success"]:
            continue
        failures += 1
        path = trace_path(args.recordings, int(record["env_id"]))
        if not path.is_file():
            missing += 1
            continue
        counts[attribute_record(record, load_trace(path), heads, config).stage] += 1
    print(f"{failures} failures of {len(results['episodes'])} episodes ({checkpoint}):")
    for stage in STAGES:
        print(f"  {STAGE_TITLES[stage]:<15} {counts[stage]}")
    if missing:
        print(f"  no recording    {missing}", file=sys.stderr)
    if stopped_steps:
        print(f"stopped by itself in {len(stopped_steps)} episodes, after {sum(stopped_steps) / len(stopped_steps):.0f}"
              " steps on average")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
