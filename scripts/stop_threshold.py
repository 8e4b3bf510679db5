"""What a plainly flown evaluation would have scored with a lower STOP threshold, computed exactly offline.

    python scripts/stop_threshold.py runs/eval20_gs-fpv-mem.json --taus 0.5 0.4 0.3 0.2
    python scripts/stop_threshold.py runs/eval19_k_dev.json runs/eval19_k_dev_rec     # a file without P(stop)

The paper's policy says STOP when P(stop) > 0.5. With a threshold tau <= 0.5 the policy would say STOP at the
first step where P(stop) > tau, which is never later than where it stopped; up to that step it flies exactly as
recorded. So a `gsmn eval --json` file (its trajectories, and the P(stop) the policy acted on at every step, which
evaluations keep since 2026-11-27, twentieth session) gives each episode's outcome at any such tau, without flying
it again. For an older file, its `--record` folder gives the model's P(stop) (a plain GSMN only: an ensemble's
recording holds one network's P(stop), not the mean it acted on). The P(stop) is checked against the recorded
STOPs at 0.5 first. Prints success, landmark success and, against 0.5, episodes fixed and broken.

    python scripts/stop_threshold.py runs/eval20_gs-fpv.json --write 0.2 runs/eval20_gs-fpv_tau0.2.json

`--write TAU OUT` also writes the evaluation as flown at TAU, in the form of `gsmn eval --json` (each episode cut
at its STOP, its summary recomputed, "stop_threshold": TAU), for scripts/results_table.py and the dashboard.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from gsmn.attribution import load_trace, trace_path  # noqa: E402
from gsmn.evaluation import write_json  # noqa: E402
from gsmn.task.metrics import goal_distance, landmark_success, sign_test, success, summarize  # noqa: E402


def stop_step(stop_probability: np.ndarray, tau: float, last: int) -> int:
    """The step at which a policy with threshold tau says STOP: the first with P(stop) > tau, or the recorded end."""
    above = np.flatnonzero(stop_probability[:last + 1] > tau)
    return int(above[0]) if above.size else last


def outcome(episode: dict, stop_probability: np.ndarray, tau: float, radius: float) -> tuple[bool, bool, bool]:
    """(success, landmark success, said STOP) of the episode flown with threshold tau <= 0.5."""
    return outcome_at(episode, stop_step(stop_probability, tau, len(episode["trajectory"]) - 1), radius)


def outcome_at(episode: dict, t: int, radius: float) -> tuple[bool, bool, bool]:
    """(success, landmark success, said STOP) of the episode ended at step t of its recorded flight."""
    last = len(episode["trajectory"]) - 1
    xy = episode["trajectory"][t][:2]
    landmark, start = (episode["landmark_x"], episode["landmark_y"]), (episode["start_x"], episode["start_y"])
    stopped = t < last or episode["stopped"]
    return success(xy, landmark, start, episode["side"], radius), landmark_success(xy, landmark, radius), stopped


def flown_at(episode: dict, stop_probability: np.ndarray, tau: float, radius: float) -> dict:
    """The episode record as the policy with threshold tau <= 0.5 would have flown it: cut at its STOP."""
    last = len(episode["trajectory"]) - 1
    t = stop_step(stop_probability, tau, last)
    if t == last:
        return dict(episode)
    ok, at_landmark, _ = outcome_at(episode, t, radius)
    x, y = episode["trajectory"][t][:2]
    actions = [list(a) for a in episode["actions"][:t + 1]]
    actions[-1][2] = True
    return {**episode, "final_x": x, "final_y": y, "steps": t, "stopped": True, "success": ok,
            "landmark_success": at_landmark, "goal_distance": goal_distance((x, y), (episode["goal_x"],
                                                                                      episode["goal_y"])),
            "trajectory": episode["trajectory"][:t + 1], "actions": actions,
            "stop_probabilities": [float(q) for q in stop_probability[:t + 1]],
            **({"member_stop_probabilities": episode["member_stop_probabilities"][:t + 1]}
               if episode.get("member_stop_probabilities") is not None else {})}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", help="a `gsmn eval --json` file (a plain network or an ensemble with its P(stop))")
    parser.add_argument("record", nargs="?", help="its --record folder (only for a file without stop_probabilities)")
    parser.add_argument("--taus", type=float, nargs="+", default=[0.5, 0.45, 0.4, 0.35, 0.3, 0.25, 0.2, 0.15, 0.1])
    parser.add_argument("--radius", type=float, default=None, help="default: the evaluation's own success radius")
    parser.add_argument("--write", nargs=2, metavar=("TAU", "OUT"), help="write the evaluation as flown at TAU")
    args = parser.parse_args()
    if any(not 0 < tau <= 0.5 for tau in args.taus + ([float(args.write[0])] if args.write else [])):
        parser.error("every tau must be in (0, 0.5]: a higher one could stop later than the recorded flight")
    results = json.loads(Path(args.results).read_text())
    if "stop_threshold" in results:
        parser.error(f"this file is an evaluation re-scored at tau {results['stop_threshold']:g} (--write); "
                     "give the evaluation it was written from")
    radius = args.radius or results["config"]["task"]["success_radius"]
    episodes = results["episodes"]
    in_file = all(e.get("stop_probabilities") is not None for e in episodes)
    if not in_file:
        if args.record is None:
            parser.error("this file keeps no P(stop) per step: give its --record folder")
        if results.get("mirror_ensemble") or results.get("ensemble_with"):
            parser.error("an ensemble's recording holds one network's P(stop), not the one it acted on")
    probabilities = {}
    for e in episodes:
        if in_file:
            p = np.asarray(e["stop_probabilities"], np.float64)
        else:
            p = load_trace(trace_path(args.record, e["env_id"])).stop_probability
        said = [bool(a[2]) for a in e["actions"]]
        if len(p) != len(said) or any((q > 0.5) != s for q, s in zip(p, said, strict=True) if abs(q - 0.5) > 1e-4):
            parser.error(f"environment {e['env_id']}: the recorded P(stop) does not give the recorded STOPs")
        probabilities[e["env_id"]] = p
    base = {e["env_id"]: outcome(e, probabilities[e["env_id"]], 0.5, radius)[0] for e in episodes}
    mismatched = [e["env_id"] for e in episodes if base[e["env_id"]] != e["success"]]
    if mismatched:
        parser.error(f"at 0.5 the recorded outcome is not reproduced in environments {mismatched[:5]}")
    n = len(episodes)
    print(f"{n} episodes of {args.results}; success radius {radius:g} m")
    print("| tau | success | landmark success | said STOP | fixed vs 0.5 | broken vs 0.5 | sign test p |")
    print("|---|---|---|---|---|---|---|")
    best = None  # (successes, tau): the most successes, ties to the higher tau (nearer the paper's 0.5)
    for tau in args.taus:
        rows = {e["env_id"]: outcome(e, probabilities[e["env_id"]], tau, radius) for e in episodes}
        ok = sum(r[0] for r in rows.values())
        best = max(best or (ok, tau), (ok, tau))
        fixed = sum(rows[i][0] and not base[i] for i in rows)
        broken = sum(base[i] and not rows[i][0] for i in rows)
        print(f"| {tau:g} | {100 * ok / n:.1f} % ({ok}) | {100 * sum(r[1] for r in rows.values()) / n:.1f} % | "
              f"{sum(r[2] for r in rows.values())} | {fixed} | {broken} | {sign_test(fixed, broken):.2g} |")
    print(f"most successes (ties: the higher tau): tau {best[1]:g}, {best[0]} of {n}")
    if args.write:
        tau, out = float(args.write[0]), Path(args.write[1])
        flown = [flown_at(e, probabilities[e["env_id"]], tau, radius) for e in episodes]
        written = {**results, "stop_threshold": tau, "summary": summarize(flown, radius).to_dict(), "episodes": flown}
        write_json(out, written)  # atomically, as `gsmn eval --json` writes
        print(f"wrote {out}: {sum(e['success'] for e in flown)} of {n} at tau {tau:g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
