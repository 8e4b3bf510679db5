"""Before/after of two checkpoints on the same environments, from `gsmn eval --json` files (several files a side
are merged: an evaluation run in pieces), as markdown, with failure attribution when the recordings are given
(`gsmn analyze compare`).

    gsmn analyze compare --before runs/eval_a.json runs/eval_a_rest.json --after runs/eval_b.json \\
        --records-before runs/eval_a_rec --records-after runs/eval_b_rec --name "test split (750)" --png out.png

A table (success, landmark success, mean and median distance; fixed and broken episodes) and, with recordings, the
failures per attribution stage on each side. The environments of the two sides must be the same.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from gsmn.analysis.failures import stage_counts
from gsmn.attribution import STAGE_COLOURS, STAGES, reported_stages
from gsmn.evaluation import merge_results


def load(paths: list[Path]) -> dict:
    return merge_results([json.loads(p.read_text()) for p in paths])


def compare(before: dict, after: dict) -> dict:
    """Episode by episode: which failures the after side fixed and which successes it broke."""
    a = {e["env_id"]: e for e in after["episodes"]}
    pairs = [(e, a[e["env_id"]]) for e in before["episodes"]]
    return {
        "fixed": sum(1 for b, x in pairs if not b["success"] and x["success"]),
        "broken": sum(1 for b, x in pairs if b["success"] and not x["success"]),
        "landmark_fixed": sum(1 for b, x in pairs if not b["landmark_success"] and x["landmark_success"]),
        "landmark_broken": sum(1 for b, x in pairs if b["landmark_success"] and not x["landmark_success"]),
    }


def flown(result: dict) -> str:
    """What an evaluation flew: its checkpoint, the ensemble's other checkpoints, whether mirrored."""
    names = [result["checkpoint"] or "checkpoints/gsmn", *result.get("ensemble_with", [])]
    text = " + ".join(f"`{c}`" for c in names)
    return text + (" (mirror ensemble)" if result.get("mirror_ensemble") else "")


def markdown(name: str, before: dict, after: dict, c: dict, stages: tuple[dict, dict] | None) -> str:
    b, a = before["summary"], after["summary"]
    n = len(before["episodes"])
    lines = ["| episodes | | success % | landmark % | mean distance m | median distance m |",
             "|---|---|---|---|---|---|"]
    for side, s, result in (("before", b, before), ("after", a, after)):
        p = s.get("pruned") or s
        lines.append(f"| {name} ({n}) | {side}: {flown(result)} | {s['success']:.2f} ({p['success']:.2f}) | "
                     f"{s['landmark_success']:.2f} ({p['landmark_success']:.2f}) | {s['mean_distance']:.2f} | "
                     f"{s['median_distance']:.2f} |")
    lines += ["", f"Fixed {c['fixed']}, broken {c['broken']} (landmark success: {c['landmark_fixed']} gained, "
              f"{c['landmark_broken']} lost); unambiguous subset in brackets."]
    if stages:
        lines += ["", "| failed because | before | after |", "|---|---|---|"]
        lines += [f"| {k} | {stages[0][k]} | {stages[1][k]} |" for k in reported_stages(*stages)]
    return "\n".join(lines)


def compare_report(before_files: list[Path], after_files: list[Path], records_before: Path | None = None,
                   records_after: Path | None = None, name: str = "episodes", png: Path | None = None) -> str:
    """The before/after markdown; with `png`, also the figure (matplotlib). ValueError if the files of a side do
    not merge or the sides cover different environments."""
    try:
        before, after = load(before_files), load(after_files)
    except ValueError as e:
        raise ValueError(f"cannot merge: {e}") from e
    if sorted(before["env_ids"]) != sorted(after["env_ids"]):
        raise ValueError(f"the two sides cover different environments ({len(before['env_ids'])} and "
                         f"{len(after['env_ids'])}); evaluate them on the same ones")
    stages = None
    if records_before and records_after:
        (sb, mb), (sa, ma) = stage_counts(before, records_before), stage_counts(after, records_after)
        if mb or ma:
            print(f"failures without a recording: {mb} before, {ma} after", file=sys.stderr)
        stages = (sb, sa)
    if png:
        empty = dict.fromkeys(STAGES, 0)
        figure([(name, {"summary": before["summary"], "stages": stages[0] if stages else empty},
                 {"summary": after["summary"], "stages": stages[1] if stages else empty})], png)
        print(f"wrote {png}", file=sys.stderr)
    return markdown(name, before, after, compare(before, after), stages)


def rows_stages(rows: list[tuple[str, dict, dict]]) -> tuple[str, ...]:
    """The stages to show for these before/after rows: `reported_stages` over every side's counts."""
    return reported_stages(*(e["stages"] for _, before, after in rows for e in (before, after)))


def figure(rows: list[tuple[str, dict, dict]], out: Path) -> None:
    """Success and landmark success, mean distance, and failures by attribution, before and after, for each set."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stages = rows_stages(rows)
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    ticks, names = [], []
    for g, (name, before, after) in enumerate(rows):
        for k, e in enumerate((before, after)):
            x = 2.6 * g + k
            s = e["summary"] or {}
            ok, lm = s.get("success") or 0.0, s.get("landmark_success") or 0.0
            axes[0].bar(x, lm, 0.8, color="#cfe8d8", edgecolor="#1e8449", label="landmark success" if x == 0 else None)
            axes[0].bar(x, ok, 0.8, color="#1e8449", label="success" if x == 0 else None)
            axes[1].bar(x, s.get("mean_distance") or 0.0, 0.8, color="#7f8c8d" if k == 0 else "#34495e")
            bottom = 0
            for stage in stages:
                n = e["stages"].get(stage, 0)
                axes[2].bar(x, n, 0.8, bottom=bottom, color=STAGE_COLOURS.get(stage, "#999"),
                            label=stage.replace("_", " ") if x == 0 else None)
                bottom += n
            ticks.append(x)
            names.append(f"{'before' if k == 0 else 'after'}\n{name.split(' (')[0]}")
    for ax in axes:
        ax.set_xticks(ticks, names, fontsize=8)
    axes[0].set_ylim(0, 100)
    axes[0].set_ylabel("% of episodes")
    axes[0].set_title("Success and landmark success")
    axes[0].legend(fontsize=8)
    axes[1].set_ylabel("m")
    axes[1].set_title("Mean distance to the goal")
    axes[2].set_ylabel("failed episodes")
    axes[2].set_title("Failures by attribution")
    axes[2].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
