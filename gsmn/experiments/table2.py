"""`gsmn experiment table2`: the command line of the Table 2 programme. The systems and the recipe they share are
`gsmn.experiments.recipe`, the programme that trains, evaluates and keeps them `gsmn.experiments.programme`, the
tables of their kept evaluations `gsmn.experiments.table`.
"""

from __future__ import annotations

from pathlib import Path

from gsmn.experiments.programme import Layout, keep_latest, run_programme, run_system
from gsmn.experiments.recipe import BY_NAME, DEFAULT_SHIP, RECIPES, SYSTEMS, system_configs
from gsmn.experiments.table import modules_markdown, orderings_markdown, table1_markdown, table_markdown


# -- command line -----------------------------------------------------------------------------------------------
def add_parser(sub) -> None:
    import argparse

    t = sub.add_parser("table2", help="train and evaluate GSMN, its four ablations and GSMN + pose noise with one "
                                      "recipe (the paper's Table 2); resumes wherever it stopped")
    t.add_argument("--out", default="runs/table2", help="run folders and expert data (may be lost; rebuilt)")
    t.add_argument("--ship", default=str(DEFAULT_SHIP),
                   help="where each system's latest stage and its evaluation are kept (default: checkpoints/table2)")
    t.add_argument("--systems", default=",".join(s.name for s in SYSTEMS),
                   help="which systems, in order (default: all: %(default)s)")
    t.add_argument("--parallel", type=int, default=2,
                   help="systems trained side by side, the cores shared out among them (on two cores: one thread "
                        "each; 1: one at a time with both)")
    t.add_argument("--recipe", choices=sorted(RECIPES), default="paper", help="the budget (tiny: seconds, for tests)")
    t.add_argument("--git-commit", action="store_true",
                   help="commit each system's stage copy as soon as it is written (so a new machine resumes it)")
    t.add_argument("--keep-latest", action="store_true",
                   help="copy each system's last finished epoch or iteration over its stage copy (with --git-commit, "
                        "commit it) and exit; safe while the programme runs: before a machine is lost")
    t.add_argument("--table", action="store_true",
                   help="print Table 2 (dev) and the Table 1 rows (test) from the kept evaluations and exit")
    t.add_argument("--system", help=argparse.SUPPRESS)  # one system in this process: what the programme runs
    t.add_argument("--threads", type=int, default=2, help=argparse.SUPPRESS)
    t.add_argument("--device", default="cpu",
                   help="where the systems train: cpu, cuda or cuda:N (supervised and DAggerFM epochs; rollouts and "
                        "evaluation stay on the CPU); a run may change it when it resumes")
    t.set_defaults(func=cmd_table2)


def check_device(device: str) -> None:
    """`--device` as `train.device` takes it, and present on this machine."""
    from gsmn.training.supervised import training_device

    try:
        system_configs(SYSTEMS[0], RECIPES["tiny"], 1, device)  # train.device's own check of the name
    except ValueError as e:
        raise ValueError(f"--device {device!r}: {e}") from None
    try:
        training_device(device)
    except ValueError as e:
        raise ValueError(str(e).replace("--train.device", "--device")) from None


def cmd_table2(args) -> int:
    layout = Layout(Path(args.out), Path(args.ship))
    recipe = RECIPES[args.recipe]
    if args.table:
        print(table_markdown(layout.ship))
        print()
        print(orderings_markdown(layout.ship))
        print()
        print(modules_markdown(layout.ship))
        print()
        print(table1_markdown(layout.ship))
        return 0
    if args.system:
        check_device(args.device)
        from gsmn.model.runtime import keep_freed_memory

        keep_freed_memory()
        run_system(BY_NAME[args.system], layout, recipe, args.threads, args.git_commit,
                   log=lambda line: print(line, flush=True), device=args.device)
        return 0
    names = [n.strip() for n in args.systems.split(",") if n.strip()]
    unknown = [n for n in names if n not in BY_NAME]
    if unknown:
        raise ValueError(f"unknown system(s) {unknown}; choose from {', '.join(BY_NAME)}")
    if args.keep_latest:
        keep_latest(layout, [BY_NAME[n] for n in names], args.git_commit)
        return 0
    if args.parallel < 1:
        raise ValueError("--parallel must be at least 1")
    check_device(args.device)  # before any collection, where this machine has no such device
    return run_programme(layout, recipe, args.recipe, [BY_NAME[n] for n in names], args.parallel, args.git_commit,
                         device=args.device)

