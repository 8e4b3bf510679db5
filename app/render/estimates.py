"""How long an evaluation or a fine-tuning run will take, before and while it runs (pure; the Failures and Fine-tune
tabs say it). Before: from the jobs of the same kind this server's record holds as finished (an episode's seconds, a
run's seconds per iteration with the same settings); nothing is guessed where the record has none. While: from the
job's own pace so far.
"""

from __future__ import annotations

import statistics

from app.jobs.db import Evaluation, Run

RECENT = 5  # the finished jobs a rate is the median of


def duration_words(seconds: float) -> str:
    """'about 40 s', 'about 6 min', 'about 1 h 20 min'."""
    if seconds < 90:
        return f"about {max(5, round(seconds / 5) * 5):.0f} s"
    minutes = round(seconds / 60)
    if minutes < 90:
        return f"about {minutes} min"
    return f"about {minutes // 60} h {minutes % 60:02d} min"


def seconds_per_episode(evaluations: list[Evaluation], workers: int = 1) -> float | None:
    """The median seconds an episode took in the last finished evaluations flown here (not imported ones), scaled to
    `workers` processes; None when there are none."""
    rates = [(e.finished - e.started) / e.done for e in evaluations
             if e.status == "finished" and e.source != "import" and e.started and e.finished and e.done > 0]
    return statistics.median(rates[-RECENT:]) if rates else None


def evaluation_estimate(episodes: int, evaluations: list[Evaluation]) -> str:
    """Before an evaluation: how long `episodes` take here, from the record."""
    rate = seconds_per_episode(evaluations)
    if rate is None:
        return "No evaluation has finished on this server yet: the first one's pace sets the estimates."
    return (f"{episodes} episode{'s' if episodes != 1 else ''} take {duration_words(episodes * rate)} here "
            f"({rate:.1f} s an episode in the last evaluations).")


def remaining(done: float, total: float, elapsed: float) -> str:
    """While a job runs: what is left at its pace so far ('' until it has done something to measure)."""
    if done <= 0 or total <= done or elapsed <= 0:
        return ""
    return f"{duration_words(elapsed / done * (total - done))} left"


def evaluation_remaining(e: Evaluation, now: float, evaluations: list[Evaluation]) -> str:
    """An evaluation running: what is left, at its own pace, or before its first episode at the record's."""
    if e.started is None:
        return ""
    if e.done:
        return remaining(e.done, e.total, now - e.started)
    rate = seconds_per_episode(evaluations)
    return f"{duration_words(rate * e.total)} in all at the last evaluations' pace" if rate else ""


def _same_settings(a: dict, b: dict) -> bool:
    return {k: v for k, v in a.items() if k != "iterations"} == {k: v for k, v in b.items() if k != "iterations"}


def run_estimate(settings: dict, runs: list[Run]) -> str:
    """Before a run: how long its iterations take here, from finished runs with the same settings but their number
    of iterations."""
    rates = [(r.finished - r.started) / r.settings["iterations"] for r in runs
             if r.status == "finished" and r.started and r.finished and r.settings.get("iterations")
             and _same_settings(r.settings, settings)]
    iterations = int(settings.get("iterations") or 0)
    if not rates or iterations < 1:
        return "No run with these settings has finished on this server yet: the first one's pace sets the estimates."
    rate = statistics.median(rates[-RECENT:])
    return (f"{iterations} iteration{'s' if iterations != 1 else ''} take {duration_words(iterations * rate)} here "
            f"({duration_words(rate).removeprefix('about ')} an iteration in runs with these settings).")


def run_remaining(r: Run, now: float) -> str:
    """A run going: what is left at its own pace (its progress fraction, the supervisor's)."""
    fraction = float((r.progress or {}).get("fraction", 0.0))
    if r.started is None or fraction < 0.02:
        return ""
    return remaining(fraction, 1.0, now - r.started)
