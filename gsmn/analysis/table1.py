"""The paper's Table 1 as markdown, from `gsmn eval --json` files, beside the paper's figures (`gsmn analyze table1`).

Each file gives one row: success, landmark success, mean and median distance to the goal, and in brackets the
same on the pruned (unambiguous) subset. Files must cover the same environments: the rows of one table have to be
comparable, so a mix is refused.
"""

from __future__ import annotations

# The paper's Table 1: (success, landmark success, mean distance, median distance), pruned in the second tuple.
PAPER = {
    "gsmn": ((83.47, 89.33, 2.67, 1.21), (87.21, 93.38, 2.24, 1.12)),
    "gsmn-no-plan": ((69.89, 84.76, 3.19, 1.63), (71.03, 89.56, 2.91, 1.65)),
    "gs-fpv": ((24.93, 56.80, 7.23, 5.14), (27.35, 56.03, 7.15, 4.97)),
    "gs-fpv-mem": ((28.67, 60.13, 6.72, 4.34), (33.82, 65.74, 6.11, 3.95)),
    "oracle": ((87.87, 98.40, 0.74, 0.67), (86.47, 98.10, 0.78, 0.73)),
    "avg-forward": ((3.32, 49.00, 11.96, 12.23), (3.98, 14.12, 13.43, 13.71)),
    "random-point": ((2.13, 9.59, 15.14, 15.05), None),
    "random-landmark": ((17.31, 17.31, 13.26, 13.37), None),
}
NAMES = {"gsmn": "GSMN", "gsmn-no-plan": "GSMN w/o J_plan", "gs-fpv": "GS-FPV", "gs-fpv-mem": "GS-FPV-MEM",
         "oracle": "Oracle (expert)", "avg-forward": "Avg # steps fwd", "random-point": "Random point",
         "random-landmark": "Random landmark"}
KEYS = ("success", "landmark_success", "mean_distance", "median_distance")
HEADER = ("| system | success % (ours) | success % (paper) | landmark % (ours) | landmark % (paper) "
          "| mean dist m (ours) | mean (paper) | median m (ours) | median (paper) |", "|" + "---|" * 9)


def _ours(summary: dict, i: int) -> str:
    pruned = summary.get("pruned")
    text = f"{summary[KEYS[i]]:.2f}"
    return text + (f" ({pruned[KEYS[i]]:.2f})" if pruned else "")


def _paper(system: str, i: int) -> str:
    full, pruned = PAPER.get(system, (None, None))
    if full is None:
        return ""
    return f"{full[i]:.2f}" + (f" ({pruned[i]:.2f})" if pruned else "")


def table(results: list[dict], labels: dict[str, str], files: list[str] | None = None) -> str:
    """One row per result; a row is named by labels[its file] or labels[its system], else the system's name.
    ValueError if the results cover different environments."""
    if len({tuple(r["env_ids"]) for r in results}) != 1:
        counts = ", ".join(f"{f}: {len(r['env_ids'])}" for f, r in zip(files or range(len(results)), results,
                                                                        strict=True))
        raise ValueError(f"the files cover different environments ({counts}); evaluate them on the same ones")
    lines = list(HEADER)
    for r, file in zip(results, files or [None] * len(results), strict=True):
        system = r["system"]
        cells = [labels.get(file, labels.get(system, NAMES.get(system, system)))]
        for i in range(4):
            cells += [_ours(r["summary"], i), _paper(system, i)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
