"""How long the dashboard takes to analyse a whole evaluation (docs/dashboard.md, "Analysis"): two shipped
500-episode evaluations of Table 1's test environments (GSMN and GSMN without J_plan, Table 2's recipe) imported into
a throw-away record, then the analysis the page and `GET /api/evaluations/{id}/slices?versus=` answer (slices,
landmark x side, confusion matrices, the versus table over up to two attributes combined), read from the record each
time (a new `Analyses`, so nothing kept in memory is reused), and the episodes behind one confusion cell. Medians of
several runs.

    python scripts/bench_analysis.py [--runs 7]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=7)
    p.add_argument("--first", default="table2/gsmn/test")
    p.add_argument("--versus", default="table2/no-plan/test")
    args = p.parse_args()
    from app.jobs.analysis import Analyses
    from app.jobs.db import Database
    from gsmn.config import preset

    with tempfile.TemporaryDirectory() as folder:
        db = Database(Path(folder) / "gsmn.sqlite")
        analyses = Analyses(db, preset("paper"), ROOT / "checkpoints")
        t = time.perf_counter()
        first, other = analyses.import_shipped(args.first), analyses.import_shipped(args.versus)
        imported = time.perf_counter() - t
        whole, cell = [], []
        for _ in range(args.runs):
            fresh = Analyses(db, preset("paper"), ROOT / "checkpoints")
            t = time.perf_counter()
            found = fresh.analysis(first.id, other.id)
            whole.append(time.perf_counter() - t)
            asked, reads = next(iter(found["confusion"]["stopped_at"].items()))
            t = time.perf_counter()
            fresh.episodes(first.id, None, ("stopped_at", asked, next(iter(reads))), False)
            cell.append(time.perf_counter() - t)
        db.close()
    print(f"{first.total} episodes ({first.label}) against {other.total} ({other.label})")
    print(f"importing both shipped files into the record (once): {imported:.2f} s")
    print(f"analysis with versus, from the record: median {1e3 * statistics.median(whole):.0f} ms "
          f"(min {1e3 * min(whole):.0f}, max {1e3 * max(whole):.0f}) over {args.runs} runs")
    print(f"the episodes of one confusion cell: median {1e3 * statistics.median(cell):.0f} ms")


if __name__ == "__main__":
    main()
