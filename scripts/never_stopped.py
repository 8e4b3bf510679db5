"""The episodes of an evaluation that never stopped: how close the drone came to the goal, where the goal map's
peak was at that step, and the highest P(stop) while within the success radius of the goal.

    python scripts/never_stopped.py runs/eval_gsmn_stop_it12.json runs/eval_gsmn_stop_it12_rec

Reads each episode's trajectory from the evaluation JSON and `stop_probability`, `goal_peak_rc` from its
recording (`gsmn eval ... --record DIR`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from gsmn.attribution import cell_centre, load_trace, trace_path
from gsmn.config import RunConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("evaluation", help="the JSON of `gsmn eval --json`")
    parser.add_argument("records", help="the folder of `gsmn eval --record`")
    parser.add_argument("--radius", type=float, default=1.8, help="'near the goal' (m): the expert's stop radius")
    args = parser.parse_args()
    evaluation = json.loads(Path(args.evaluation).read_text())
    config = RunConfig.from_dict(evaluation["config"])
    field, n = config.world.field_size, config.model.map_size
    rows = []
    for e in evaluation["episodes"]:
        if e["stopped"]:
            continue
        trace = load_trace(trace_path(args.records, e["env_id"]))
        goal = np.array([e["goal_x"], e["goal_y"]])
        steps = len(trace.goal_peak_rc)
        distance = np.linalg.norm(np.array(e["trajectory"])[:steps, :2] - goal, axis=1)
        peaks = np.array([cell_centre(int(r), int(c), field, n) for r, c in trace.goal_peak_rc])
        j = int(np.argmin(distance))
        near = distance < args.radius
        p_near = float(trace.stop_probability[:steps][near].max()) if near.any() else float("nan")
        rows.append((e["env_id"], e["side"], distance[j], float(np.linalg.norm(peaks[j] - goal)), p_near))
        print(f"env {e['env_id']:5d} {e['side']:5s}  closest {distance[j]:5.2f} m  goal peak then "
              f"{rows[-1][3]:5.2f} m from the goal  max P(stop) within {args.radius} m: {p_near:.3f}")
    near = [r for r in rows if r[2] < args.radius]
    print(f"{len(rows)} never stopped; {len(near)} came within {args.radius} m of the goal, of which "
          f"{sum(r[3] < args.radius for r in near)} with the goal map's peak within {args.radius} m of it then; "
          f"max P(stop) there below 0.3 in {sum(r[4] < 0.3 for r in near)}")


if __name__ == "__main__":
    main()
