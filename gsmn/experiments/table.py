"""Table 2 and Table 1's rows from the evaluations the programme keeps (`gsmn experiment table2 --table`): each
system beside the paper's figures with its Wilson interval, each ablation's paired sign test against the control,
the paper's orderings, the two kinds of ablation side by side, and the failures by attributed stage.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

from gsmn.experiments.recipe import (
    BY_NAME,
    EVALUATIONS,
    MODULE_ABLATIONS,
    SYSTEMS,
    TABLE1,
    kept_partial,
    read_stage,
    trained,
    training_stage,
)
from gsmn.task.metrics import sign_test, wilson

# -- the table ------------------------------------------------------------------------------------------------
PAPER = {  # Table 2 of the paper (development results): success, landmark success, mean and median distance
    "gsmn": (79.20, 86.00, 2.98, 1.21), "no-plan": (64.40, 82.00, 3.61, 1.75), "no-ground": (5.73, 17.73, 10.69, 10.64),
    "no-lang": (41.20, 57.20, 6.62, 3.37), "no-percept": (50.00, 63.73, 5.89, 2.55),
    "pose-noise": (74.40, 85.33, 3.01, 1.41),
    # the paper's -J_rel and -J_goal rows are the original code's module removals (docs/model.md)
    "no-ground-module": (5.73, 17.73, 10.69, 10.64), "no-plan-module": (64.40, 82.00, 3.61, 1.75),
}


def interval(successes: int, n: int) -> tuple[float, float]:
    """The 95 % Wilson interval of a success rate, in percent."""
    low, high = wilson(successes, n)
    return 100 * low, 100 * high


def pending(ship: Path, split: str = "dev") -> str:
    """A row not yet measured, with where its system stands: "not yet (DAggerFM iteration 7 of 15)"."""
    stage = read_stage(ship)
    if stage is None:
        return "not yet (not started)"
    kept = kept_partial(ship, split)
    if kept["episodes"]:
        return f"not yet ({len(kept['episodes'])} of {len(kept['env_ids'])} {split} environments flown)"
    return "not yet (trained, not evaluated)" if trained(stage) else f"not yet ({training_stage(stage)})"


def kept_evaluations(ship: Path) -> dict[str, dict]:
    """Each system's kept dev evaluation (`<ship>/<name>/evaluation.json`), by name, in SYSTEMS order."""
    return {s.name: json.loads((ship / s.name / "evaluation.json").read_text())
            for s in SYSTEMS if (ship / s.name / "evaluation.json").is_file()}


def table_markdown(ship: Path) -> str:
    """Table 2 from the kept evaluations: ours beside the paper's, each ablation's drop from the control with a
    paired sign test over the same environments, and the failures' attribution counts."""
    from gsmn.attribution import reported_stages

    found = kept_evaluations(ship)
    counts = {name: Counter(e["stage"] for e in result["episodes"] if e.get("stage")) for name, result in found.items()}
    stages = reported_stages(*counts.values())  # the merged stages of untrained heads only where some row has one
    lines = ["| system | success % (95 % interval) | landmark % | mean dist (m) | median dist (m) | paper: success, "
             "landmark, mean, median | drop from control (fixed / broken, sign test p) | failures by stage ("
             + ", ".join(stages) + ") |", "|---|---|---|---|---|---|---|---|"]
    control = found.get(SYSTEMS[0].name)
    for system in SYSTEMS:
        paper = " / ".join(f"{v:.2f}" for v in PAPER[system.name]) if system.name in PAPER else "(not in Table 2)"
        result = found.get(system.name)
        if result is None:
            lines.append(f"| {system.label} | {pending(ship / system.name)} | | | | {paper} | | |")
            continue
        s, eps = result["summary"], result["episodes"]
        low, high = interval(sum(e["success"] for e in eps), len(eps))
        drop = ""
        if control is not None and system.name != SYSTEMS[0].name:
            fixed, broken = paired(control["episodes"], eps)
            drop = (f"{control['summary']['success'] - s['success']:+.1f} ({fixed} / {broken}, "
                    f"p {sign_test(fixed, broken):.2g})")
        unattributed = not counts[system.name] and not all(e["success"] for e in eps)  # e.g. GS-FPV: no maps
        by_stage = ("not attributed (no maps)" if unattributed
                    else ", ".join(str(counts[system.name].get(stage, 0)) for stage in stages))
        lines.append(f"| {system.label} | {s['success']:.1f} ({low:.1f}-{high:.1f}) | {s['landmark_success']:.1f} | "
                     f"{s['mean_distance']:.2f} | {s['median_distance']:.2f} | {paper} | {drop} | {by_stage} |")
    return "\n".join(lines)


def orderings_markdown(ship: Path) -> str:
    """The paper's orderings tested on the kept evaluations: the measured ablations in the order of their drop, each
    pair of them compared over the same environments (sign test), and the environments each ablation (then pose
    noise) breaks (the control succeeds, it fails) by its attributed stage."""
    found = {name: result["episodes"] for name, result in kept_evaluations(ship).items()}
    control = found.get(SYSTEMS[0].name)
    # the objective ablations (the module removals are compared with them in `modules_markdown`)
    ablations = [s for s in SYSTEMS[1:] if s.name in found and any(k.startswith("loss.") for k in s.switch)
                 and s.name not in MODULE_ABLATIONS.values()]
    if control is None or not ablations:
        return "Orderings: not yet (they need the control and at least one ablation evaluated)."

    def rate(name: str) -> float:
        return sum(e["success"] for e in found[name]) / len(found[name])
    ranked = sorted(ablations, key=lambda s: rate(s.name))  # the largest drop first
    lines = [f"Ablations by success rate, the largest drop first (control {100 * rate(SYSTEMS[0].name):.1f} %): "
             + ", ".join(f"{s.label} ({100 * rate(s.name):.1f} %)" for s in ranked)]
    for i, a in enumerate(ranked):
        for b in ranked[i + 1:]:
            b_wins, a_wins = paired(found[a.name], found[b.name])
            lines.append(f"{b.label} succeeds where {a.label} fails in {b_wins}, the reverse in {a_wins}: sign test "
                         f"p {sign_test(b_wins, a_wins):.2g}")
    others = [s for s in SYSTEMS[1:] if s.name in found and s not in ablations and s.kind.startswith("gsmn")]
    for s in ranked + others:  # pose noise and the module removals too
        outcome = {e["env_id"]: e for e in found[s.name]}
        broken = [outcome[e["env_id"]].get("stage") for e in control
                  if e["success"] and e["env_id"] in outcome and not outcome[e["env_id"]]["success"]]
        stages = Counter(stage for stage in broken if stage)  # an evaluation without attribution has none
        lines.append(f"{s.label} breaks {len(broken)} of the control's successes: "
                     + (", ".join(f"{stage} {n}" for stage, n in stages.most_common()) or "no stage attributed"))
    return "\n".join(lines)


def modules_markdown(ship: Path) -> str:
    """The two kinds of ablation side by side (objective removed / module removed with it, as the original code) for
    J_ground and J_plan: the paper's figure, each kind's success with its Wilson interval and its paired sign test
    against the control, and the two kinds paired with each other."""
    found = {name: result["episodes"] for name, result in kept_evaluations(ship).items()}
    control = found.get(SYSTEMS[0].name)
    lines = ["| objective removed | paper (module removed) | loss removed: success % (95 % interval); vs control "
             "(fixed / broken, p) | module removed too: success % (95 % interval); vs control | module against loss "
             "(fixed / broken, p) |", "|---|---|---|---|---|"]

    def cell(name: str) -> str:
        if name not in found:
            return pending(ship / name)
        eps = found[name]
        wins = sum(e["success"] for e in eps)
        low, high = interval(wins, len(eps))
        text = f"{100 * wins / len(eps):.1f} ({low:.1f}-{high:.1f})"
        if control is not None:
            fixed, broken = paired(control, eps)
            text += f"; {fixed} / {broken}, p {sign_test(fixed, broken):.2g}"
        return text

    for loss_name, module_name in MODULE_ABLATIONS.items():
        both = ""
        if loss_name in found and module_name in found:
            fixed, broken = paired(found[loss_name], found[module_name])
            both = f"{fixed} / {broken}, p {sign_test(fixed, broken):.2g}"
        objective = BY_NAME[loss_name].label.removeprefix("GSMN without ")
        lines.append(f"| {objective} | {PAPER[module_name][0]:.2f} | {cell(loss_name)} | {cell(module_name)} | "
                     f"{both} |")
    return "\n".join(lines)


def paired(control: list[dict], other: list[dict]) -> tuple[int, int]:
    """(fixed, broken) over the environments both flew: `other` succeeds where `control` fails, and the reverse."""
    by_env = {e["env_id"]: e["success"] for e in control}
    pairs = [(by_env[e["env_id"]], e["success"]) for e in other if e["env_id"] in by_env]
    return sum(a and not c for c, a in pairs), sum(c and not a for c, a in pairs)


def table1_markdown(ship: Path) -> str:
    """Table 1's rows of the TABLE1 systems on the test environments, in docs/results.md's columns (ours and the
    paper's, pruned in brackets), and each one's paired comparison with the control."""
    from gsmn.analysis.table1 import HEADER, table

    results, files, labels, rows = [], [], {}, []
    for name in TABLE1:
        path = ship / name / EVALUATIONS["test"][1]
        if not path.is_file():
            rows.append(f"| {BY_NAME[name].label}, Table 2's recipe | {pending(ship / name, 'test')} |" + " |" * 7)
            continue
        result = json.loads(path.read_text())
        results.append({**result, "system": BY_NAME[name].kind})  # the paper's figures are keyed by model kind
        files.append(name)
        labels[name] = f"{BY_NAME[name].label}, Table 2's recipe (`checkpoints/table2/{name}`)"
    lines = table(results, labels, files).split("\n") if results else list(HEADER)
    lines += rows
    if results and files[0] == TABLE1[0]:
        for name, result in zip(files[1:], results[1:], strict=True):
            fixed, broken = paired(results[0]["episodes"], result["episodes"])
            lines.append(f"\n{BY_NAME[name].label} against {BY_NAME[TABLE1[0]].label}, paired over the same "
                         f"{len(result['episodes'])} environments: {fixed} fixed / {broken} broken, sign test p "
                         f"{sign_test(fixed, broken):.2g}")
    return "\n".join(lines)

