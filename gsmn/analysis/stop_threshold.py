"""What a plainly flown evaluation would have scored with a lower STOP threshold, computed exactly offline
(`gsmn analyze stop-threshold`).

The paper's policy says STOP when P(stop) > 0.5. With a threshold tau <= 0.5 the policy would say STOP at the
first step where P(stop) > tau, which is never later than where it stopped; up to that step it flies exactly as
recorded. So a `gsmn eval --json` file (its trajectories, and the P(stop) the policy acted on at every step) gives
each episode's outcome at any such tau, without flying it again. For a file without P(stop), its `--record` folder
gives the model's P(stop) (a plain GSMN only: an ensemble's recording holds one network's P(stop), not the mean it
acted on). The P(stop) is checked against the recorded STOPs at 0.5 first. The table: success, landmark success
and, against 0.5, episodes fixed and broken. `write` also writes the evaluation as flown at one tau, in the form of
`gsmn eval --json` (each episode cut at its STOP, its summary recomputed, "stop_threshold": tau), for
`gsmn analyze table1` and the dashboard.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gsmn.attribution import load_trace, trace_path
from gsmn.evaluation import write_json
from gsmn.task.metrics import goal_distance, landmark_success, sign_test, success, summarize

TAUS = (0.5, 0.45, 0.4, 0.35, 0.3, 0.25, 0.2, 0.15, 0.1)


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


def rescore(results_path: Path, record: Path | None = None, taus: list[float] | None = None,
            radius: float | None = None, write: tuple[float, Path] | None = None) -> str:
    """The table of an evaluation re-scored at each tau (markdown, with a first line naming the file); with `write`
    (tau, out), also the evaluation as flown at that tau, written to out. ValueError for a tau above 0.5, a file
    re-scored already, a missing recording, or P(stop) that does not give the recorded STOPs and outcomes."""
    taus = list(TAUS) if taus is None else taus
    if any(not 0 < tau <= 0.5 for tau in [*taus, *([write[0]] if write else [])]):
        raise ValueError("every tau must be in (0, 0.5]: a higher one could stop later than the recorded flight")
    results = json.loads(Path(results_path).read_text())
    if "stop_threshold" in results:
        raise ValueError(f"this file is an evaluation re-scored at tau {results['stop_threshold']:g} (--write); "
                         "give the evaluation it was written from")
    radius = radius or results["config"]["task"]["success_radius"]
    episodes = results["episodes"]
    in_file = all(e.get("stop_probabilities") is not None for e in episodes)
    if not in_file:
        if record is None:
            raise ValueError("this file keeps no P(stop) per step: give its --record folder")
        if results.get("mirror_ensemble") or results.get("ensemble_with"):
            raise ValueError("an ensemble's recording holds one network's P(stop), not the one it acted on")
    probabilities = {}
    for e in episodes:
        if in_file:
            p = np.asarray(e["stop_probabilities"], np.float64)
        else:
            p = load_trace(trace_path(record, e["env_id"])).stop_probability
        said = [bool(a[2]) for a in e["actions"]]
        if len(p) != len(said) or any((q > 0.5) != s for q, s in zip(p, said, strict=True) if abs(q - 0.5) > 1e-4):
            raise ValueError(f"environment {e['env_id']}: the recorded P(stop) does not give the recorded STOPs")
        probabilities[e["env_id"]] = p
    base = {e["env_id"]: outcome(e, probabilities[e["env_id"]], 0.5, radius)[0] for e in episodes}
    mismatched = [e["env_id"] for e in episodes if base[e["env_id"]] != e["success"]]
    if mismatched:
        raise ValueError(f"at 0.5 the recorded outcome is not reproduced in environments {mismatched[:5]}")
    n = len(episodes)
    lines = [f"{n} episodes of {results_path}; success radius {radius:g} m",
             "| tau | success | landmark success | said STOP | fixed vs 0.5 | broken vs 0.5 | sign test p |",
             "|---|---|---|---|---|---|---|"]
    best = None  # (successes, tau): the most successes, ties to the higher tau (nearer the paper's 0.5)
    for tau in taus:
        rows = {e["env_id"]: outcome(e, probabilities[e["env_id"]], tau, radius) for e in episodes}
        ok = sum(r[0] for r in rows.values())
        best = max(best or (ok, tau), (ok, tau))
        fixed = sum(rows[i][0] and not base[i] for i in rows)
        broken = sum(base[i] and not rows[i][0] for i in rows)
        lines.append(f"| {tau:g} | {100 * ok / n:.1f} % ({ok}) | {100 * sum(r[1] for r in rows.values()) / n:.1f} % | "
                     f"{sum(r[2] for r in rows.values())} | {fixed} | {broken} | {sign_test(fixed, broken):.2g} |")
    lines.append(f"most successes (ties: the higher tau): tau {best[1]:g}, {best[0]} of {n}")
    if write:
        tau, out = float(write[0]), Path(write[1])
        flown = [flown_at(e, probabilities[e["env_id"]], tau, radius) for e in episodes]
        written = {**results, "stop_threshold": tau, "summary": summarize(flown, radius).to_dict(), "episodes": flown}
        write_json(out, written)  # atomically, as `gsmn eval --json` writes
        lines.append(f"wrote {out}: {sum(e['success'] for e in flown)} of {n} at tau {tau:g}")
    return "\n".join(lines)
