"""Navigation against stopping: of each evaluation's episodes, how many flew into the success region at some step
(where a STOP would have succeeded), how many of those said STOP there, how many stopped elsewhere later and how
many never stopped; with a sign test on "entered the region" between evaluations of the same environments.

    python scripts/region_counts.py gs-fpv=runs/eval17_gs-fpv.json gs-fpv-mem=runs/eval17_gs-fpv-mem.json

Reads the trajectories of `gsmn eval --json` files (no recordings needed). A system that enters the region often
but succeeds rarely fails on its STOP, not on its navigation (docs/training.md, the baselines' order). Where the
file keeps the policy's P(stop) per step (evaluations since 2026-11-27), the last column is the median and
quartiles, over the failures that flew through the region, of the highest P(stop) there. Where it keeps a test-time
ensemble's members' own P(stop) per step (evaluations since 2026-11-28), a line under the table counts the STOPs
the averaging took away: failures that flew through the region with a step there at which one copy alone would
have said STOP (its P(stop) above 0.5) but the mean was not.
"""

from __future__ import annotations

import argparse
import json
from itertools import combinations
from pathlib import Path

import numpy as np

from gsmn.task.metrics import record_region_steps, region_stop_probability, sign_test


def members_line(missed: list[dict], regions: dict[int, list[int]]) -> str:
    """Of the failures that flew through the region, how many had a step there at which a member's P(stop) was
    above 0.5 while the ensemble's mean was not, in all and per member (member order: `Ensemble.members`)."""
    rows = []  # per failure, per member: took away a STOP at some step in the region
    for e in missed:
        members = np.asarray(e["member_stop_probabilities"], np.float64)  # (steps, members)
        there = members[[i for i in regions[e["env_id"]] if i < len(members)]]
        rows.append(((there > 0.5) & (there.mean(axis=1, keepdims=True) <= 0.5)).any(axis=0))
    lost = np.asarray(rows)
    return (f"of {len(missed)} failures that flew through the region, {int(lost.any(axis=1).sum())} had a step "
            f"there at which a member alone would have said STOP but the mean did not (per member: "
            f"{', '.join(map(str, lost.sum(axis=0)))})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("evaluations", nargs="+", help="NAME=PATH of `gsmn eval --json` files")
    parser.add_argument("--radius", type=float, default=6.0, help="the success radius (m)")
    args = parser.parse_args()
    reached: dict[str, dict[int, bool]] = {}
    averaged_away: list[str] = []
    print("| system | episodes | success | entered the region | of those: success | stopped elsewhere later | "
          "never stopped | highest P(stop) there, flown through |")
    print("|---|---|---|---|---|---|---|---|")
    for spec in args.evaluations:
        name, _, path = spec.partition("=")
        if not path:
            parser.error(f"expected NAME=PATH, got {spec!r}")
        episodes = json.loads(Path(path).read_text())["episodes"]
        regions = {e["env_id"]: record_region_steps(e, args.radius) for e in episodes}
        reached[name] = {i: bool(steps) for i, steps in regions.items()}
        n_in = sum(reached[name].values())
        ok = sum(e["success"] for e in episodes)
        missed = [e for e in episodes if reached[name][e["env_id"]] and not e["success"]]
        later = sum(e["stopped"] for e in missed)
        highest = [p for e in missed if (p := region_stop_probability(e, regions[e["env_id"]])) is not None]
        if not missed:
            spread = "-"
        elif len(highest) < len(missed):
            spread = "not kept"  # the expert, a heuristic baseline, or a file written before P(stop) was kept
        else:
            q = np.percentile(highest, [50, 25, 75])
            spread = f"{q[0]:.2f} ({q[1]:.2f}-{q[2]:.2f})"
        print(f"| {name} | {len(episodes)} | {ok} | {n_in} | {ok} ({100 * ok / max(n_in, 1):.0f} %) | {later} | "
              f"{len(missed) - later} | {spread} |")
        if missed and all(e.get("member_stop_probabilities") is not None for e in missed):
            averaged_away.append(f"{name}: " + members_line(missed, regions))
    for line in averaged_away:
        print(line)
    for (na, a), (nb, b) in combinations(reached.items(), 2):
        if a.keys() != b.keys():
            print(f"{na} vs {nb}: not the same environments")
            continue
        x = sum(a[i] and not b[i] for i in a)
        y = sum(b[i] and not a[i] for i in a)
        print(f"entered: only {na} {x}, only {nb} {y}, sign test p = {sign_test(x, y):.2g}")


if __name__ == "__main__":
    main()
