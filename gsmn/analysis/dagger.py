"""DAggerFM runs side by side, an iteration a row (`gsmn analyze dagger`): beta, the dev figures, and how many of the
iteration's own rollouts succeeded and were cut; with `dataset`, what each run's dataset holds now.

Reads RUN/log.jsonl (one record per iteration) and, with `dataset`, the episodes in RUN/dataset: how many came from
the expert store and how many are rollouts; of the rollouts (by their metadata) how many succeeded, were cut for
straying from the path, or neither (or were flown before rollouts kept their outcome), and in each group how many
carry an expert STOP label at all (a failed one that does flew on past the place where the expert said STOP).
"""

from __future__ import annotations

import json
from pathlib import Path

from gsmn.training.run import RunFolder
from gsmn.training.store import EpisodeStore


def cells(record: dict | None, n: int) -> list[str]:
    """One run's cells for one iteration; n: the run's rollouts an iteration (N_D)."""
    if record is None:
        return [""] * 5
    dev = record.get("dev", {})
    scored = "" if record.get("rollout_success") is None else (
        f"{round(record['rollout_success'] * n)} / {round(record['rollout_cut'] * n)}")
    return [f"{dev['loss_action']:.3f}" if "loss_action" in dev else ""] + [
        f"{100 * dev[k]:.0f} %" if k in dev else "" for k in ("acc_perception", "acc_grounding",
                                                               "acc_instruction_landmark")] + [scored]


def dataset_summary(run: Path) -> str:
    """What RUN/dataset holds: expert episodes, and the rollouts by outcome (with a STOP label in brackets)."""
    store = EpisodeStore(run / "dataset")
    expert = 0
    groups = {"succeeded": [0, 0], "failed and cut": [0, 0], "failed, not cut": [0, 0], "not scored": [0, 0]}
    for key in store.keys():
        meta = store.read_meta(key)
        if "iteration" not in meta:  # an episode of the expert store
            expert += 1
            continue
        if "success" not in meta:  # flown before rollouts kept their outcome
            group = "not scored"
        else:
            group = "succeeded" if meta["success"] else "failed and cut" if meta["cut"] else "failed, not cut"
        groups[group][0] += 1
        groups[group][1] += bool((store.read_labels(key)[:, 2] > 0.5).any())
    rollouts = sum(n for n, _ in groups.values())
    return (f"{run}: {expert + rollouts} episodes, {expert} from the expert store, {rollouts} rollouts: "
            + ", ".join(f"{name} {n} ({stop} with a STOP label)" for name, (n, stop) in groups.items()
                        if n or name != "not scored"))


def dagger_table(runs: list[Path], first: int = 1, dataset: bool = False) -> str:
    """The runs' iterations from `first` on, a row each (markdown); with `dataset`, a line per run's dataset."""
    logs = [{int(r["iteration"]): r for r in RunFolder(run).read_log()} for run in runs]
    n_d = [json.loads((r / "config.json").read_text())["dagger"]["rollouts_per_iteration"] for r in runs]
    head = ["iteration", "beta"]
    for r in runs:
        name = r.name.split("_dagger")[0]
        head += [f"{name} dev action loss", "perception", "grounding", "instr. landmark", "rollouts succeeded / cut"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i in sorted(set().union(*logs)):
        if i < first:
            continue
        beta = next(log[i]["beta"] for log in logs if i in log)
        row = [str(i), f"{beta:.4g}"]
        for log, n in zip(logs, n_d, strict=True):
            row += cells(log.get(i), n)
        lines.append("| " + " | ".join(row) + " |")
    if dataset:
        lines += [dataset_summary(r) for r in runs]
    return "\n".join(lines)
