"""Navigation against stopping (`gsmn analyze regions`): of each evaluation's episodes, how many flew into the success
region at some step (where a STOP would have succeeded), how many of those said STOP there, how many stopped
elsewhere later and how many never stopped; with a sign test on "entered the region" between evaluations of the
same environments.

Reads the trajectories of `gsmn eval --json` files (no recordings needed). A system that enters the region often
but succeeds rarely fails on its STOP, not on its navigation (docs/training.md, the baselines' order). Where the
file keeps the policy's P(stop) per step, the last column is the median and quartiles, over the failures that flew
through the region, of the highest P(stop) there. Where it keeps a test-time ensemble's members' own P(stop) per
step, a line under the table counts the STOPs the averaging took away: failures that flew through the region with a
step there at which one copy alone would have said STOP (its P(stop) above 0.5) but the mean was not.
"""


from __future__ import annotations

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


def region_table(evaluations: list[tuple[str, Path]], radius: float = 6.0) -> str:
    """The table for (name, `gsmn eval --json` path) pairs, then the ensembles' lines and the pairwise sign tests."""
    reached: dict[str, dict[int, bool]] = {}
    averaged_away: list[str] = []
    lines = ["| system | episodes | success | entered the region | of those: success | stopped elsewhere later | "
             "never stopped | highest P(stop) there, flown through |", "|---|---|---|---|---|---|---|---|"]
    for name, path in evaluations:
        episodes = json.loads(Path(path).read_text())["episodes"]
        regions = {e["env_id"]: record_region_steps(e, radius) for e in episodes}
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
        lines.append(f"| {name} | {len(episodes)} | {ok} | {n_in} | {ok} ({100 * ok / max(n_in, 1):.0f} %) | {later} | "
                     f"{len(missed) - later} | {spread} |")
        if missed and all(e.get("member_stop_probabilities") is not None for e in missed):
            averaged_away.append(f"{name}: " + members_line(missed, regions))
    lines += averaged_away
    for (na, a), (nb, b) in combinations(reached.items(), 2):
        if a.keys() != b.keys():
            lines.append(f"{na} vs {nb}: not the same environments")
            continue
        x = sum(a[i] and not b[i] for i in a)
        y = sum(b[i] and not a[i] for i in a)
        lines.append(f"entered: only {na} {x}, only {nb} {y}, sign test p = {sign_test(x, y):.2g}")
    return "\n".join(lines)
