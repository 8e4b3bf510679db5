"""What the page's "Failures" and "Fine-tune" tabs say, as pure functions of the recorded jobs (`app.jobs.db`): an
evaluation's label, summary and attribution bars, an episode's card, a run's table, curves and resume hint, and the
before/after comparison (HTML for viser's panels)."""

from __future__ import annotations

import html
import math

import numpy as np

from app.jobs.db import ACTIVE, FINISHED, EpisodeRow, Evaluation, Run
from app.jobs.results import same_checkpoint
from app.jobs.supervisor import resumable
from app.render.panels import region_text
from app.render.truth import TRUTH_ROW, went_wrong_text
from gsmn.attribution import STAGE_COLOURS, STAGE_TITLES, reported_stages
from gsmn.world.spec import split_of


def short_path(path: str | None) -> str:
    if path is None:
        return "the expert"
    parts = path.rstrip("/").split("/")
    return "/".join(parts[-3:]) if len(parts) > 3 else path


def error_summary(error: str | None) -> str:
    """The first line of a job's error and, when its output was attached, the last line of that (the exception)."""
    lines = [line for line in (error or "").splitlines() if line.strip()]
    if not lines:
        return ""
    return lines[0].removesuffix("; its output ends:") + (f": {lines[-1].strip()}" if len(lines) > 1 else "")


def note_html(text: str) -> str:
    return f'<div style="padding:8px;font-size:13px;opacity:.7">{html.escape(text)}</div>'


def _pct(v) -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.0f} %"


def evaluation_label(e: Evaluation) -> str:
    s = e.summary or {}
    if e.system == "oracle":
        what = "expert"
    elif e.run_id is not None:
        what = f"run-{e.run_id}"
    else:
        what = (e.checkpoint or e.system).rstrip("/").split("/")[-1]
    status = "" if e.status == FINISHED else f", {e.status}"
    return f"#{e.id} {what}: {e.label}, {_pct(s.get('success'))} success{status}"


def summary_html(e: Evaluation, stages: dict[str, int], regions: dict[str, int] | None = None) -> str:
    s = e.summary or {}
    failures = sum(stages.values())
    bars = []
    for stage in (*reported_stages(stages), "unattributed"):
        n = stages.get(stage, 0)
        if stage == "unattributed" and not n:
            continue
        width = 100 * n / failures if failures else 0
        bars.append(f'<div style="display:flex;align-items:center;gap:6px;font-size:12px" data-stage="{stage}">'
                    f'<span style="width:104px">{"no maps recorded" if stage == "unattributed" else stage_title(stage)}'
                    f'</span>'
                    f'<span style="flex:1;background:#eee;height:10px;border-radius:2px">'
                    f'<span style="display:block;width:{width:.0f}%;height:10px;'
                    f'background:{_STAGE_COLOURS.get(stage, "#999")};'
                    f'border-radius:2px"></span></span><b style="width:24px;text-align:right">{n}</b></div>')
    distance = s.get("mean_distance")
    distance = "n/a" if distance is None or math.isnan(distance) else f"{distance:.1f} m"
    hint = resume_hint(e)
    return (f'<div class="gsmn-evaluation" data-id="{e.id}" data-status="{e.status}" style="font-size:13px">'
            f"<div><b>{e.done}/{e.total}</b> episodes · success <b>{_pct(s.get('success'))}</b> · landmark "
            f"{_pct(s.get('landmark_success'))} · mean distance {distance}</div>"
            f'<div style="margin:4px 0 2px;font-weight:600">Failures by attribution ({failures})</div>'
            f"{''.join(bars)}{region_summary(regions)}"
            + (f'<div class="gsmn-resumable" style="font-size:12px;margin-top:4px">{hint}</div>' if hint else "")
            + "</div>")


def resume_hint(e: Evaluation) -> str:
    """For a resumable evaluation with episodes left: that Resume flies the rest (else "")."""
    if not resumable(e) or e.done >= e.total:
        return ""
    if not e.done:
        return f"Stopped before any episode ended: <b>Resume</b> (above) flies all {e.total}."
    return (f"Stopped at {e.done} of {e.total} episodes: <b>Resume</b> (above) keeps those and flies the other "
            f"{e.total - e.done}.")


def region_summary(regions: dict[str, int] | None) -> str:
    """One line under the attribution bars: how many failures flew through the success region without a STOP there
    (stopping failures) and how many never entered it (navigation failures)."""
    if not regions or not regions.get("entered", 0) + regions.get("never", 0):
        return ""
    unknown = regions.get("unknown", 0)
    rest = f"; {unknown} recorded without it" if unknown else ""
    return (f'<div class="gsmn-regions" style="font-size:12px;margin-top:4px" data-entered="{regions["entered"]}" '
            f'data-never="{regions["never"]}">Success region: <b>{regions["entered"]}</b> flew through it without a '
            f'STOP there, <b>{regions["never"]}</b> never entered it{rest}</div>')


_STAGE_COLOURS = {**STAGE_COLOURS, "unattributed": "#999"}


def rescue_html(table: dict, running: dict[str, str] | None = None) -> str:
    """The rescue table under an evaluation's attribution bars (`gsmn.analysis.rescue.rescue_table`): per truth
    intervention, how many of the failures attributed to each stage it turned into successes, of those flown so far;
    `running`: the interventions still flying, by flag, with their status."""
    flags = list(table["interventions"])
    if not flags:
        return ""
    from gsmn.analysis.intervention import FLAG_LABELS

    def cell(r: dict) -> str:
        if not r["of"]:
            return "<td>-</td>"
        return (f'<td title="95 % interval {100 * r["low"]:.0f} to {100 * r["high"]:.0f} %"><b>{r["rescued"]}</b>/'
                f'{r["of"]}</td>')

    head = "".join(f"<th>{html.escape(FLAG_LABELS.get(f, f))}</th>" for f in flags)
    rows = [f"<tr><td>{html.escape(stage_title(s) or 'not attributed')}</td>"
            + "".join(cell(table["interventions"][f]["per_stage"][s]) for f in flags) + "</tr>"
            for s in table["stages"]]
    rows.append("<tr><td><b>all failures</b></td>" + "".join(cell(table["interventions"][f]["all"]) for f in flags)
                + "</tr>")
    flying = "".join(f"; {html.escape(FLAG_LABELS.get(f, f))} {html.escape(status)}" for f, status in
                     (running or {}).items())
    return (f'<div class="gsmn-rescue" style="font-size:12px;margin-top:6px"><div style="font-weight:600">'
            f"Rescued by a true map (failures flown again from the start with it){flying}</div>"
            f'<table style="border-collapse:collapse;font-size:12px"><tr><th>attributed to</th>{head}</tr>'
            f"{''.join(rows)}</table><div>rescued / flown; a failure attributed to a stage should be rescued most "
            "by that stage's true map</div></div>")


SORTS = {"flown order": None, "environment id": lambda r: r.env_id,
         "distance to goal, far first": lambda r: -r.goal_distance,
         "distance to goal, near first": lambda r: r.goal_distance}


def sort_rows(rows: list[EpisodeRow], order: str) -> list[EpisodeRow]:
    """The failure browser's rows in the order chosen (`SORTS`), ties in the order flown."""
    key = SORTS[order]
    return list(rows) if key is None else sorted(rows, key=key)


def stage_title(stage: str | None) -> str:
    """A stage as the attribution bars name it ("goal_or_control" -> "goal or control")."""
    return STAGE_TITLES.get(stage, stage.replace("_", " ")) if stage else ""


def episode_label(r: EpisodeRow) -> str:
    """A row's button: the outcome and, for a failure, the stage it is attributed to come first, so that a button
    too narrow for the whole line loses the distance, never the verdict (the hint has it all: `episode_hint`)."""
    mark = "✓ success" if r.success else f"✗ {stage_title(r.stage)}" if r.stage else "✗ failure"
    return f"▶ {r.env_id} {mark} · {r.side} of the {r.landmark} · {r.goal_distance:.1f} m"


def episode_hint(r: EpisodeRow) -> str:
    """The whole row in words, shown when the pointer rests on its button."""
    verdict = "success" if r.success else "failure" + (f", attributed to: {stage_title(r.stage)}" if r.stage else "")
    return (f"Environment {r.env_id}: {verdict}; asked for the {r.side} side of the {r.landmark}, ended "
            f"{r.goal_distance:.1f} m from the goal after {r.steps} steps. Click to fly it again in the live view.")


def episode_colour(r: EpisodeRow) -> str:
    """The row button's colour: a success and a failure told apart at a glance."""
    return "teal" if r.success else "red"


def both_readings(r: EpisodeRow) -> str:
    """Where a failure's attribution (read from its final maps) and its success-region passage both hold, why:
    the drone passed where a STOP would have succeeded, and its maps went wrong later, or never made it stop."""
    if r.success or not r.region_steps or not r.stage or r.stage == "control":
        return ""
    a = r.attribution or {}
    peak = (f" (its goal map then peaked {a['goal_peak_error']:.1f} m from the goal)"
            if r.stage in ("goal", "grounding_or_goal") and a.get("goal_peak_error") is not None else "")
    return (f"<div class='gsmn-both' style='font-size:12px;margin:2px 0 4px'>Both readings hold: the attribution reads "
            f"the maps at the episode's end{peak}, while on the way the drone flew through the success region "
            f"without a STOP, where one would have succeeded. It failed to stop first; the maps it ended with "
            f"explain why it did not come back.</div>")


def _attribution_rows(a: dict) -> list[tuple[str, str]]:
    """The attribution's evidence, of the named landmark and the goal, and the whole maps' figures apart."""
    if a.get("perceived", False) is None:
        perceived = "seen; no trained reading (trained without J_percept)"
    else:
        perceived = ("yes" if a["perceived"] else "no") + (
            f" (read as {html.escape(a['top_class'])}, the landmark ranks {a['landmark_class_rank']})"
            if a["observed"] else " (never seen)")
    if a.get("grounded", False) is None:
        grounded = "no trained reading (trained without J_ground)"
    else:
        grounded = ("yes" if a["grounded"] else "no") + f" (P(named) {a['p_named']:.2f}" + (
            f" vs {a['p_named_other']:.2f} at the {html.escape(a['other_landmark'])})" if a.get("other_landmark")
            else ")")
    goal = ("no trained reading (trained without J_plan)" if a.get("goal_right", False) is None
            else ("right" if a["goal_right"] else "wrong")
            + f" (peak {a['goal_peak_error']:.1f} m from the goal, P {a['goal_peak_p']:.2f})")
    rows = [("named landmark perceived", perceived), ("named landmark grounded", grounded), ("goal map", goal)]
    if a.get("failed_from"):  # from the per-step agreement with the ground truth (app.render.truth)
        rows.append((TRUTH_ROW, went_wrong_text(a["failed_from"], ("<b>", "</b>"))))
    return rows


def episode_html(r: EpisodeRow, note: str) -> str:
    a = r.attribution or {}
    rows = [("instruction", html.escape(r.instruction)), ("success", "yes" if r.success else "no"),
            ("landmark success", "yes" if r.landmark_success else "no"),
            ("distance to goal", f"{r.goal_distance:.1f} m"), ("ambiguous", "yes" if r.ambiguous else "no"),
            ("ended", f"said STOP after {r.steps} steps" if r.stopped else f"horizon after {r.steps} steps")]
    if not r.success and r.region_steps is not None:
        rows.append(("success region", region_text(r.region_steps, r.region_stop_p, ("<b>", "</b>"))))
    if a:
        rows += _attribution_rows(a)
    stage = r.stage or ("success" if r.success else "not attributed (no maps recorded)")
    both = both_readings(r)
    verdict = (f"<div style='font-weight:600;color:{_STAGE_COLOURS.get(r.stage or '', '#1e8449')}'>"
               f"{html.escape(STAGE_TITLES.get(stage, stage))}</div>"
               f"<div style='margin-bottom:4px'>{html.escape(a.get('reason', ''))}</div>") if a or r.success else ""
    table = "".join(f"<tr><td style='opacity:.7;padding-right:8px'>{k}</td><td>{v}</td></tr>" for k, v in rows)
    return (f'<div class="gsmn-episode" data-env="{r.env_id}" data-evaluation="{r.evaluation_id}" '
            f'style="font-size:13px;padding-right:8px"><div style="font-weight:600">Environment {r.env_id}</div>'
            f"{verdict}{both}<table>{table}</table><div class='gsmn-replay' style='margin-top:4px'>{note}</div></div>")


def run_resume_hint(r: Run) -> str:
    """For a cancelled or failed run the dashboard started: where Resume takes it up (else "")."""
    if not resumable(r):
        return ""
    done = len(r.metrics or [])
    return (f" **Resume** continues it from iteration {done + 1} of {r.settings['iterations']}" if done else
            " **Resume** starts it again (no iteration had finished)") + "; what its folder saved is kept."


def runs_html(runs: list[Run]) -> str:
    if not runs:
        return note_html("No run yet.")
    head = "".join(f"<th style='text-align:left;padding-right:6px'>{h}</th>" for h in
                   ("run", "status", "progress", "environments", "loss"))
    body = []
    for r in reversed(runs[-12:]):
        p = r.progress or {}
        loss = r.metrics[-1]["train"].get("loss") if r.metrics else None
        envs = f"{len(r.env_ids)} chosen" if r.env_ids else "train split"
        body.append(f"<tr data-run='{r.id}' data-status='{r.status}'><td>run-{r.id}</td><td>{r.status}</td>"
                    f"<td>{100 * float(p.get('fraction', 0)):.0f} %</td><td>{envs}</td>"
                    f"<td>{'' if loss is None else f'{loss:.3f}'}</td></tr>")
    return f"<table class='gsmn-runs' style='font-size:12px'><tr>{head}</tr>{''.join(body)}</table>"


def curve_scales(run: Run | None, planned: int | None = None) -> dict:
    """The chart's x axis spans the run's planned iterations (or, before any run, the `planned` iterations of the
    form), from 1: the curves grow across it as the run goes (uPlot's own range for a single point or none is
    0-100, which read as a hundred iterations). Losses have their own axis on the left; the two shares theirs,
    0 to 1, on the right."""
    if run is not None:
        planned = int(run.settings.get("iterations") or 0)
    last = max((int(m.get("iteration", k + 1)) for k, m in enumerate(run.metrics)), default=1) if run else 1
    return {"x": {"time": False, "range": (1.0, float(max(planned or 0, last, 2)))}, "loss": {"auto": True},
            "share": {"auto": False, "range": (0.0, 1.05)}}  # headroom: the top tick "1" is not clipped


CURVE_SERIES = ({"label": "iteration"}, {"label": "loss", "stroke": "#2870f5", "width": 2, "scale": "loss"},
                {"label": "action loss", "stroke": "#e08020", "width": 2, "scale": "loss"},
                {"label": "learner's share of steps", "stroke": "#1e8449", "width": 2, "dash": [4, 3],
                 "scale": "share"},
                {"label": "rollouts succeeded", "stroke": "#8e44ad", "width": 2, "scale": "share"})
CURVE_AXES = ({"label": "iteration"}, {"scale": "loss", "label": "loss"},
              {"scale": "share", "label": "share (0-1)", "side": 1, "grid": {"show": False}})
# What the form's DAggerFM settings are (paper: Learning, DAggerFM), said beside them.
SETTING_HINTS = {
    "N_D": "N_D: rollouts flown per iteration, each adding its steps to the dataset",
    "M": "M: the dataset's size in rollouts; the oldest are dropped past it (at least N_D)",
    "beta0": "beta0: in iteration i the expert flies with probability beta0^i, the model otherwise",
}


def curve_data(metrics: list[dict]) -> tuple[np.ndarray, ...]:
    """The run's curves per iteration: loss, action loss, the learner's share of the steps flown and the share
    of the iteration's rollouts that succeeded (NaN where a record lacks a figure)."""
    if not metrics:
        return np.zeros(1), *(np.full(1, np.nan) for _ in range(4))
    it = np.array([m.get("iteration", k + 1) for k, m in enumerate(metrics)], np.float64)
    loss = np.array([m.get("train", {}).get("loss", np.nan) for m in metrics], np.float64)
    action = np.array([m.get("train", {}).get("loss_action", np.nan) for m in metrics], np.float64)
    learner = np.array([m.get("learner_step_fraction", np.nan) for m in metrics], np.float64)
    succeeded = np.array([m.get("rollout_success", np.nan) for m in metrics], np.float64)
    return it, loss, action, learner, succeeded


ACCURACY_CURVES = ("perception", "grounding", "goal", "instruction_landmark", "instruction_side")


def accuracy_data(metrics: list[dict]) -> tuple[np.ndarray, ...]:
    """The run's dev accuracy per objective and iteration (the paper's Figure 4: perception, grounding, goal,
    instruction landmark and side), from each iteration's record; NaN where it has none (no dev set, or an objective
    that is off)."""
    if not metrics:
        return np.zeros(1), *(np.full(1, np.nan) for _ in ACCURACY_CURVES)
    it = np.array([m.get("iteration", k + 1) for k, m in enumerate(metrics)], np.float64)
    return it, *(np.array([_finite(m.get("dev", {}).get(f"acc_{name}")) for m in metrics], np.float64)
                 for name in ACCURACY_CURVES)


def _finite(x) -> float:
    try:
        return float(x) if x is not None and math.isfinite(float(x)) else np.nan
    except (TypeError, ValueError):
        return np.nan


def compare_html(c: dict, after: Evaluation | None, run: Run | None = None) -> str:
    def cell(b: dict) -> str:
        mark = "<b style='color:#1e8449'>✓</b>" if b["success"] else "<b style='color:#c0392b'>✗</b>"
        return f"{mark} {b['goal_distance']:.1f} m{' · ' + stage_title(b['stage']) if b['stage'] else ''}"

    if after is not None and after.status in ACTIVE:
        return note_html(f"Rerunning: {after.done} of {after.total} episodes done.")
    rows = "".join(f"<tr><td>{r['env_id']}</td><td>{cell(r['before'])}</td><td>{cell(r['after'])}</td></tr>"
                   for r in c["episodes"])

    def dist(v) -> str:
        return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.1f} m"

    return (f"<div class='gsmn-compare' data-before='{c['before']}' data-after='{c['after']}' style='font-size:12px'>"
            f"{who_note(c, run)}{trained_on_note(c, run)}"
            f"<div style='font-size:13px;margin-bottom:4px'>Evaluation {c['before']} → {c['after']}: success "
            f"<b>{_pct(c['before_success'])} → {_pct(c['after_success'])}</b>, mean distance "
            f"{dist(c['before_mean_distance'])} → {dist(c['after_mean_distance'])}; {c['fixed']} fixed, "
            f"{c['broken']} broken.</div><table><tr><th style='text-align:left'>env</th><th style='text-align:left'>"
            f"before</th><th style='text-align:left'>after</th></tr>{rows}</table>"
            f"<div style='font-size:11px;opacity:.75;margin-top:4px'>Replay a row with the buttons below.</div></div>")


def who_note(c: dict, run: Run | None) -> str:
    """Which checkpoints before and after are, and a warning when before is not the one the run started from (the
    difference would then mix a change of checkpoint with the fine-tune)."""
    before, after = short_path(c.get("before_checkpoint")), short_path(c.get("after_checkpoint"))
    if run is not None:
        after = f"run-{run.id}, fine-tuned from {short_path(run.init_checkpoint)}"
    out = (f"<div class='gsmn-who' style='margin-bottom:4px'><b>Before</b>: evaluation {c['before']}, "
           f"{html.escape(before)} · <b>After</b>: evaluation {c['after']}, {html.escape(after)}.</div>")
    if run is not None and not same_checkpoint(c.get("before_checkpoint"), run.init_checkpoint):
        out += (f"<div class='gsmn-unfair' style='margin-bottom:4px;color:#c0392b'>Before is not the checkpoint "
                f"run-{run.id} started from: the difference mixes the change of checkpoint with the fine-tune. "
                f"Press Before/after again to fly {html.escape(short_path(run.init_checkpoint))} on these "
                f"episodes.</div>")
    return out


def trained_on_note(c: dict, run: Run | None) -> str:
    """Which episodes the run trained on, so before/after on them is not read as held-out performance."""
    if run is None:
        return ""
    compared = {r["env_id"] for r in c["episodes"]}
    if not run.env_ids:
        train = sum(split_of(e) == "train" for e in compared)
        held = "held out from it" if not train else f"{train} of them from the train split it trained on"
        return (f"<div class='gsmn-trained-on' style='margin-bottom:4px'>run-{run.id} trained on the train split; "
                f"these {len(compared)} episodes are {held}.</div>")
    trained = compared & set(run.env_ids)
    test = sorted(e for e in run.env_ids if split_of(e) != "train")
    held_out = (f"<div class='gsmn-test-trained' style='margin-bottom:4px;color:#c0392b'>run-{run.id} trained on "
                f"{len(test)} {'/'.join(sorted({split_of(e) for e in test}))} environment"
                f"{'s' if len(test) != 1 else ''}: they are no longer held out, and no figure on them measures "
                f"generalisation.</div>") if test else ""
    if trained == compared:
        what = (f"all {len(compared)} of these episodes are ones run-{run.id} trained on: the figures are on its "
                f"training episodes, not held-out performance")
    elif trained:
        what = f"{len(trained)} of these {len(compared)} episodes are ones run-{run.id} trained on"
    else:
        what = f"none of these episodes were trained on (run-{run.id} trained on {len(run.env_ids)} others)"
    return f"{held_out}<div class='gsmn-trained-on' style='margin-bottom:4px;color:#9a6b00'>{what}.</div>"
