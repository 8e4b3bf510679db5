"""Plot the development-set accuracy curves of supervised training runs (the paper's Figure 4).

    .venv/bin/pip install -e .[docs]       # matplotlib
    .venv/bin/python scripts/plot_curves.py runs/gsmn_sup runs/gsmn_sup_b1 --label GSMN --out docs/accuracy_curves.png

Each argument group is one panel: the run folders listed before a `--label` are read in order and their epochs
concatenated (a run continued from another's checkpoint in a new folder counts on from where it left off). A
`.jsonl` file is read as a run's log itself. `--columns N` lays the panels out N to a row. Figure 4 of the Table 2
programme, from the stage copies (a DAggerFM copy keeps its supervised log as `run/supervised_log.jsonl`):

    python scripts/plot_curves.py --columns 3 --out docs/accuracy_curves_table2.png \
        checkpoints/table2/gsmn/run/supervised_log.jsonl --label GSMN ...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

CURVES = [("acc_perception", "Perception", "tab:red"), ("acc_grounding", "Grounding", "tab:blue"),
          ("acc_goal", "Planning (goal)", "tab:brown"), ("acc_instruction_landmark", "Instruction: landmark",
                                                         "tab:purple"),
          ("acc_instruction_side", "Instruction: side", "tab:green")]


def read_runs(folders: list[Path]) -> tuple[list[dict], str]:
    """The dev records of the runs, in order, and the x axis's unit: 'DAggerFM iteration' when every logged record
    is a DAggerFM iteration (`gsmn train dagger`), else 'Epoch'."""
    records, logged, dagger = [], 0, True
    for folder in folders:
        log = folder if folder.suffix == ".jsonl" else folder / "log.jsonl"
        for line in log.read_text().splitlines():
            if line.strip():
                record = json.loads(line)
                logged += 1
                dagger = dagger and "iteration" in record
                if "dev" in record:
                    records.append(record["dev"])
    return records, "DAggerFM iteration" if logged and dagger else "Epoch"


def parse_panels(argv: list[str]) -> tuple[list[tuple[str, list[Path]]], Path]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/accuracy_curves.png"))
    parser.add_argument("--columns", type=int, default=0, help="panels to a row (default: all in one row)")
    args, rest = parser.parse_known_args(argv)
    panels, folders = [], []
    it = iter(rest)
    for token in it:
        if token == "--label":
            panels.append((next(it), folders))
            folders = []
        else:
            folders.append(Path(token))
    if folders:
        panels.append(("", folders))
    if not panels:
        parser.error("name at least one run folder")
    return panels, args.out, args.columns


def main(argv: list[str] | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels, out, columns = parse_panels(argv)
    columns = min(columns or len(panels), len(panels))
    rows = -(-len(panels) // columns)
    fig, grid = plt.subplots(rows, columns, figsize=(5.2 * columns, 3.6 * rows), squeeze=False, sharey=True)
    axes = list(grid.flat)[: len(panels)]
    for ax in list(grid.flat)[len(panels):]:
        ax.set_visible(False)
    runs = [read_runs(folders) for _, folders in panels]
    longest = max((len(records) for records, _ in runs), default=1)  # one x axis: a shorter run shows as shorter
    for ax, (label, _), (records, unit) in zip(axes, panels, runs, strict=True):
        epochs = list(range(1, len(records) + 1))
        for key, name, colour in CURVES:
            values = [r[key] for r in records if key in r]
            if values and (key != "acc_goal" or any(values)):
                ax.plot(epochs[: len(values)], values, marker="o", color=colour, label=name)
        ax.plot(epochs, [r["loss_action"] for r in records], marker="s", ls="--", color="black",
                label="action loss (dev)")
        ax.set(title=label, xlabel=unit, ylim=(0, 1), xlim=(0, longest + 1))
        ax.grid(axis="y", ls="--", alpha=0.6)
    for row in grid:
        row[0].set_ylabel("Dev accuracy")
    handles = {}  # every curve drawn in any panel (a run without J_plan has no goal curve), once each
    for ax in axes:
        for handle, name in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(name, handle)
    axes[-1].legend(handles.values(), handles.keys(), loc="lower right", fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
