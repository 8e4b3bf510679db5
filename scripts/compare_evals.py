"""Before/after of two checkpoints on the same environments, from `gsmn eval --json` files (several files a side
are merged: an evaluation run in pieces), as markdown, with failure attribution when the recordings are given.

    .venv/bin/python scripts/compare_evals.py --before runs/eval_a.json runs/eval_a_rest.json \\
        --after runs/eval_b.json --records-before runs/eval_a_rec --records-after runs/eval_b_rec \\
        --name "test split (750)" --png docs/before_after_test.png

Prints a table (success, landmark success, mean and median distance; fixed and broken episodes) and, with
recordings, the failures per attribution stage on each side. The environments of the two sides must be the same.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from gsmn.attribution import STAGES, reported_stages
from gsmn.evaluation import merge_results

sys.path.insert(0, str(Path(__file__).resolve().parent))
from attribution_counts import stage_counts  # noqa: E402


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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, nargs="+", required=True)
    ap.add_argument("--after", type=Path, nargs="+", required=True)
    ap.add_argument("--records-before", type=Path, default=None, help="the before evaluation's --record folder")
    ap.add_argument("--records-after", type=Path, default=None, help="the after evaluation's --record folder")
    ap.add_argument("--name", default="episodes", help="what the episodes are, for the table")
    ap.add_argument("--png", type=Path, default=None, help="also draw the before/after figure here (matplotlib)")
    args = ap.parse_args(argv)
    try:
        before, after = load(args.before), load(args.after)
    except ValueError as e:
        print(f"cannot merge: {e}", file=sys.stderr)
        return 2
    if sorted(before["env_ids"]) != sorted(after["env_ids"]):
        print(f"the two sides cover different environments ({len(before['env_ids'])} and {len(after['env_ids'])});"
              " evaluate them on the same ones", file=sys.stderr)
        return 2
    stages = None
    if args.records_before and args.records_after:
        (sb, mb), (sa, ma) = stage_counts(before, args.records_before), stage_counts(after, args.records_after)
        if mb or ma:
            print(f"failures without a recording: {mb} before, {ma} after", file=sys.stderr)
        stages = (sb, sa)
    print(markdown(args.name, before, after, compare(before, after), stages))
    if args.png:
        from finetune_failures import figure

        empty = dict.fromkeys(STAGES, 0)
        figure([(args.name, {"summary": before["summary"], "stages": stages[0] if stages else empty},
                 {"summary": after["summary"], "stages": stages[1] if stages else empty})], args.png)
        print(f"wrote {args.png}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
