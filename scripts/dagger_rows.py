"""DAggerFM runs side by side, an iteration a row: beta, the dev figures, and how many of the iteration's own
rollouts succeeded and were cut (the table of docs/training.md's DAggerFM sections); with --dataset, what each
run's dataset holds now.

    python scripts/dagger_rows.py runs/gs-fpv-mem_dagger_s28 runs/gs-fpv_dagger_s28 --dataset

Reads RUN/log.jsonl (one record per iteration) and, with --dataset, the episodes in RUN/dataset: how many came from
the expert store and how many from rollouts, and how many hold a STOP label at all (a rollout cut for straying
from the path ends without one).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def rows(run: Path) -> dict[int, dict]:
    out = {}
    for line in (run / "log.jsonl").read_text().splitlines():
        if line.strip():
            record = json.loads(line)
            out[int(record["iteration"])] = record
    return out


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
    files = sorted((run / "dataset").glob("*.npz"))
    from_rollouts = [f for f in files if f.name.startswith("dagger_")]
    with_stop = 0
    for f in files:
        with np.load(f, allow_pickle=False) as z:
            with_stop += bool((z["actions"][:, 2] > 0.5).any())
    return (f"{run}: {len(files)} episodes, {len(files) - len(from_rollouts)} from the expert store, "
            f"{len(from_rollouts)} rollouts; {with_stop} hold a STOP label")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="DAggerFM run folders")
    parser.add_argument("--first", type=int, default=1, help="first iteration to print")
    parser.add_argument("--dataset", action="store_true", help="also summarise each run's dataset")
    args = parser.parse_args()
    logs = [rows(r) for r in args.runs]
    n_d = [json.loads((r / "config.json").read_text())["dagger"]["rollouts_per_iteration"] for r in args.runs]
    head = ["iteration", "beta"]
    for r in args.runs:
        name = r.name.split("_dagger")[0]
        head += [f"{name} dev action loss", "perception", "grounding", "instr. landmark", "rollouts succeeded / cut"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for i in sorted(set().union(*logs)):
        if i < args.first:
            continue
        beta = next(log[i]["beta"] for log in logs if i in log)
        row = [str(i), f"{beta:.4g}"]
        for log, n in zip(logs, n_d, strict=True):
            row += cells(log.get(i), n)
        print("| " + " | ".join(row) + " |")
    if args.dataset:
        for r in args.runs:
            print(dataset_summary(r))


if __name__ == "__main__":
    main()
