"""Keep a copy of a training run's checkpoint after every epoch or DAggerFM iteration, for averaging.

    python scripts/keep_iterations.py runs/gsmn_dagger_avg &     # beside `gsmn train dagger --run runs/gsmn_dagger_avg`

Polls RUN/checkpoint/meta.json and copies the checkpoint (weights, config, vocabulary, meta; not the Adam state)
to RUN_itN when its iteration (or epoch) N has no copy yet. A checkpoint is replaced by a rename, so a copy is
kept only if the run's meta.json was the same before and after it (and the same as the copy's); one taken while
the checkpoint was being replaced is dropped and taken again on the next poll. Runs
until killed; `scripts/average_checkpoints.py` averages the copies (docs/training.md, "Averaging DAggerFM
iterations").
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from gsmn.model.checkpoint import OPTIMIZER_FILE


def iteration_of(meta_text: str) -> int | None:
    """The DAggerFM iteration (or supervised epoch) a checkpoint's meta.json says it was written after, or None."""
    metrics = json.loads(meta_text).get("metrics", {})
    n = metrics.get("iteration", metrics.get("epoch"))
    return None if n is None else int(n)


def keep_once(run: Path) -> Path | None:
    """Copy the run's checkpoint to RUN_itN if it is new; returns the copy, or None."""
    meta = run / "checkpoint" / "meta.json"
    try:
        before = meta.read_text()
        n = iteration_of(before)
    except (OSError, json.JSONDecodeError):  # not written yet, or being replaced
        return None
    dst = run.parent / f"{run.name}_it{n}"
    if n is None or dst.exists():
        return None
    tmp = run.parent / f".{dst.name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        shutil.copytree(run / "checkpoint", tmp, ignore=shutil.ignore_patterns(OPTIMIZER_FILE))
        unchanged = meta.read_text() == before == (tmp / "meta.json").read_text()
    except OSError:
        unchanged = False
    if not unchanged:  # replaced while copying: try again next time
        shutil.rmtree(tmp, ignore_errors=True)
        return None
    tmp.rename(dst)
    return dst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="the run folder of `gsmn train ... --run`")
    parser.add_argument("--every", type=float, default=10.0, help="seconds between polls")
    args = parser.parse_args()
    while True:
        kept = keep_once(args.run)
        if kept is not None:
            print(time.strftime("%H:%M:%S"), "kept", kept, flush=True)
        time.sleep(args.every)


if __name__ == "__main__":
    main()
