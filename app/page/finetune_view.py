"""The page's "Fine-tune" tab (viser; the tab's jobs UI thread, `app.page.jobs_view`): launch DAggerFM on the
failures selected, watch its progress and curves, cancel it, fly its checkpoint, and rerun the same episodes
before/after side by side. What the tab says is `app.render.jobs_panels`' (pure functions).
"""

from __future__ import annotations

import html
import time

import viser
import viser.uplot

from app.jobs.db import ACTIVE, FAILED, FINISHED, Run
from app.jobs.results import before_for_run, has_config, same_checkpoint
from app.jobs.settings import RUN_PRESETS, run_settings
from app.live.commands import RunnerError
from app.render.estimates import run_estimate, run_remaining
from app.render.jobs_panels import (
    CURVE_AXES,
    CURVE_SERIES,
    SETTING_HINTS,
    accuracy_data,
    compare_html,
    curve_data,
    curve_scales,
    error_summary,
    note_html,
    run_resume_hint,
    runs_html,
    short_path,
)
from app.render.panels import error_html
from gsmn.world.spec import split_of

ENV_TRAIN = "train split"


class FinetuneTab:
    """The Fine-tune tab's part of `app.page.jobs_view.JobsView` (its controls are attributes of the view)."""

    def _build_finetune(self, gui, panel) -> None:
        with panel.add_tab("Fine-tune", viser.Icon.SCHOOL):
            with gui.add_folder("DAggerFM from a checkpoint"):
                self.run_checkpoint = gui.add_dropdown("Start from", self._checkpoint_choices(expert=False))
                self.run_preset = gui.add_dropdown("Preset", tuple(RUN_PRESETS), initial_value="tiny",
                                                   hint="tiny: a minute or two here; small: tens of minutes; paper: "
                                                        f"the original's {RUN_PRESETS['paper'].iterations} iterations")
                s = RUN_PRESETS["tiny"]
                self.run_iterations = gui.add_number("Iterations", s.iterations, min=1, max=10000, step=1)
                self.run_nd = gui.add_number("N_D (rollouts/iter)", s.rollouts_per_iteration, min=1, step=1,
                                             hint=SETTING_HINTS["N_D"])
                self.run_m = gui.add_number("M (dataset size)", s.dataset_size, min=1, step=1, hint=SETTING_HINTS["M"])
                self.run_beta0 = gui.add_number("beta0", s.beta0, min=0.0, max=1.0, step=0.01,
                                                hint=SETTING_HINTS["beta0"])
                gui.add_markdown("<span style='font-size:12px;opacity:.8'>" + "<br>".join(SETTING_HINTS.values())
                                 + ".</span>")
                self.run_lr = gui.add_number("Learning rate", s.learning_rate, min=1e-6, max=1.0, step=1e-5)
                self.run_mirror = gui.add_number("Mirrored share", s.mirror, min=0.0, max=1.0, step=0.05,
                                                 hint="the share of training episodes mirrored east-west, left and "
                                                      "right swapped (not in the paper; the shipped GSMN's last "
                                                      "iterations used 0.5)")
                self.run_envs = gui.add_dropdown("Environments", (ENV_TRAIN,))
                self.run_buttons = gui.add_button_group("Run", ("Launch", "Cancel", "Resume"))
                self.run_estimate = gui.add_markdown("")
                self.run_progress = gui.add_progress_bar(0.0, visible=False)
                self.run_status = gui.add_markdown("A run trains in its own process; one at a time.")
                self.curves = gui.add_uplot(
                    data=curve_data([]), series=CURVE_SERIES, title="Per iteration", aspect=1.5,
                    scales=curve_scales(None, s.iterations), axes=CURVE_AXES)
                self.accuracies = gui.add_uplot(
                    data=accuracy_data([]),
                    series=({"label": "iteration"}, {"label": "perception", "stroke": "#8e44ad", "width": 2},
                            {"label": "grounding", "stroke": "#16a085", "width": 2},
                            {"label": "goal", "stroke": "#e08020", "width": 2},
                            {"label": "instruction landmark", "stroke": "#2870f5", "width": 2},
                            {"label": "side", "stroke": "#c0392b", "width": 2, "dash": [4, 3]}),
                    title="Dev accuracy per objective (the paper's Figure 4), per iteration", aspect=1.6,
                    scales={**curve_scales(None, s.iterations), "y": {"auto": False, "range": [0, 1]}},
                    axes=({"label": "iteration"}, {}))
            with gui.add_folder("Runs"):
                self.runs_table = gui.add_html("")
                self.run_choice = gui.add_dropdown("Finished run", ("(none yet)",))
                self.run_actions = gui.add_button_group("Checkpoint", ("Fly with it", "Before/after"))
                self.run_note = gui.add_markdown("")
            with gui.add_folder("Before / after"):
                self.compare = gui.add_html(note_html("Before/after reruns the failures' evaluation with the "
                                                         "finished run's checkpoint and shows both side by side."))
                self.compare_env = gui.add_dropdown("Environment", ("(none yet)",))
                self.compare_replay = gui.add_button_group("Replay", ("Before", "After"))
                self.compare_note = gui.add_markdown("")

    def _launch(self) -> None:
        choice = self.run_checkpoint.value
        checkpoint = self.viewer.checkpoint_of(choice)
        env_ids = None
        if self.run_envs.value != ENV_TRAIN:
            env_ids = list(self._selected_failures)
        try:
            settings = self._form_settings()
            r = self.jobs.start_run(settings, checkpoint, env_ids or None,
                                    self.evaluation_id if env_ids else None)
        except (RunnerError, ValueError) as err:
            self.run_status.content = error_html(f"**Not started:** {html.escape(str(err))}")
            return
        where = f"{len(env_ids)} failures of evaluation {self.evaluation_id}" if env_ids else "the train split"
        self.run_status.content = (f"Run {r.id} started from {html.escape(short_path(r.init_checkpoint))} on {where}."
                                   + self._launch_warnings(r, env_ids))
        self._refresh()

    def _form_settings(self):
        return run_settings(self.run_preset.value, iterations=int(self.run_iterations.value),
                            rollouts_per_iteration=int(self.run_nd.value), dataset_size=int(self.run_m.value),
                            beta0=float(self.run_beta0.value), learning_rate=float(self.run_lr.value),
                            mirror=float(self.run_mirror.value))

    def _show_run_estimate(self, runs: list[Run]) -> None:
        """Before a run: how long the one in the form would take here (app.render.estimates)."""
        if any(r.status in ACTIVE for r in runs):
            self.run_estimate.content = ""
            return
        try:
            settings = self._form_settings()
        except (RunnerError, ValueError):
            return
        self.run_estimate.content = f"*{run_estimate(settings.to_dict(), runs)}*"

    def _launch_warnings(self, run, env_ids: list[int] | None) -> str:
        """What a run launched on failures should say at once: failures of another checkpoint, or environments of
        the test or dev split, which the run then trains on."""
        if not env_ids:
            return ""
        out = []
        source = self.jobs.db.evaluation(self.evaluation_id) if self.evaluation_id else None
        if source is not None and not same_checkpoint(source.checkpoint, run.init_checkpoint):
            out.append(f"These failures are {html.escape(short_path(source.checkpoint))}'s, not the starting "
                       "checkpoint's: Before/after will first fly the starting checkpoint on them.")
        held = sorted({split_of(e) for e in env_ids} - {"train"})
        if held:
            out.append(f"It trains on {'/'.join(held)} environments: they stop being held out.")
        return "".join(f"<br>⚠ {w}" for w in out)

    def _cancel_run(self) -> None:
        active = self.jobs.db.runs(ACTIVE)
        if not active:
            self.run_status.content = "No run is going."
            return
        try:
            self.jobs.cancel_run(active[-1].id)
        except RunnerError as err:
            self.run_status.content = error_html(html.escape(str(err)))

    def _resume_run(self) -> None:
        """Continue the latest run (the one the status line shows) if it was cancelled or failed."""
        runs = self.jobs.db.runs()
        if not runs:
            self.run_status.content = "No run to resume yet."
            return
        try:
            self.jobs.resume_run(runs[-1].id)
        except RunnerError as err:
            self.run_status.content = error_html(f"**Not resumed:** {html.escape(str(err))}")
            return
        self._refresh()

    def _run_action(self, action: str) -> None:
        run_id = self._run_choices.get(self.run_choice.value)
        run = self.jobs.db.run(run_id) if run_id else None
        if run is None or run.status != FINISHED:
            self.run_note.content = "No finished run yet."
            return
        name = f"Model: run-{run.id}"
        if action == "Fly with it":
            self._refresh_checkpoints()
            if name in self.viewer.policy.options:
                self.viewer.policy.value = name
                self.run_note.content = (f"The Episode panel's policy is now **run-{run.id}**: press **Run** there, "
                                         "or replay a failure.")
            else:  # a first-person baseline's run: evaluated here, not flown in the live view
                self.run_note.content = (f"run-{run.id} is a first-person baseline: the live view cannot fly it "
                                         "(it builds no map to show); evaluate it in the Failures tab, or use "
                                         "Before/after.")
            return
        self._before_after(run)

    def _before_after(self, run) -> None:
        """Rerun the run's episodes with its checkpoint, beside the checkpoint it started from on the same ones: when
        the failures came from another checkpoint's evaluation, that one is flown first, so the change of checkpoint
        is never credited to the fine-tune."""
        baseline_id = run.source_evaluation_id or self.evaluation_id
        baseline = self.jobs.db.evaluation(baseline_id) if baseline_id is not None else None
        if baseline is None:
            self.run_note.content = error_html("No evaluation to compare with: evaluate a checkpoint first.")
            return
        before = before_for_run(self.jobs.db, run, baseline)
        start = short_path(run.init_checkpoint)
        try:  # flown the way the evaluation it reruns was (plain or as a mirror ensemble, its camera look)
            if before is None:
                e = self.jobs.start_evaluation(run.init_checkpoint, None, env_ids=list(baseline.env_ids),
                                               mirror_ensemble=baseline.mirror_ensemble, like=baseline)
                self.run_note.content = (
                    f"The failures came from evaluation {baseline.id} of **{short_path(baseline.checkpoint)}**, "
                    f"but run-{run.id} started from **{start}**. Evaluation {e.id} flies {start} on the same "
                    f"{len(baseline.env_ids)} environments first; press **Before/after** again once it is done.")
                self._refresh()
                return
            e = self.jobs.start_evaluation(run.checkpoint, None, baseline_id=before.id, run_id=run.id,
                                           mirror_ensemble=before.mirror_ensemble,
                                           like=before if has_config(before) else baseline)
        except RunnerError as err:
            self.run_note.content = error_html(f"**Not started:** {html.escape(str(err))}")
            return
        self.compare_ids = (before.id, e.id)
        self.run_note.content = (f"Evaluation {e.id} reruns the episodes of evaluation {before.id} ({start}, where "
                                 f"run-{run.id} started) with run-{run.id}.")
        self._refresh()

    def _compare_replay(self, which: str) -> None:
        """Fly a before/after row again in the live view: the evaluation before the run, or the one after."""
        if self.compare_ids is None or not self.compare_env.value.isdigit():
            self.compare_note.content = "No before/after yet."
            return
        evaluation_id = self.compare_ids[0 if which == "Before" else 1]
        row = self.jobs.db.episode(evaluation_id, int(self.compare_env.value))
        if row is None:
            self.compare_note.content = f"Environment {self.compare_env.value} has no episode in evaluation " \
                                        f"{evaluation_id} yet."
            return
        self.compare_note.content = (f"Replaying environment {row.env_id} as flown {which.lower()} the run "
                                     f"(evaluation {evaluation_id}) in the live view; its card is in Failures.")
        self._replay(row)

    def _refresh_runs(self, runs: list[Run]) -> None:
        self.runs_table.content = runs_html(runs)
        self._show_run_estimate(runs)
        active = [r for r in runs if r.status in ACTIVE]
        shown = active[-1] if active else (runs[-1] if runs else None)
        if shown is not None:
            p = shown.progress or {}
            self.run_progress.visible = shown.status in ACTIVE
            self.run_progress.value = 100.0 * float(p.get("fraction", 0.0))
            text = html.escape(p.get("text", "starting"))
            if shown.status in ACTIVE:
                left = run_remaining(shown, time.time())
                self.run_status.content = f"**Run {shown.id}** (running): {text}{f', {left}' if left else ''}."
            else:
                self.run_status.content = f"**Run {shown.id}** {shown.status}" + (
                    f": checkpoint **run-{shown.id}**." if shown.status == FINISHED else
                    "." + (f" {html.escape(error_summary(shown.error))}" if shown.status == FAILED else "")
                    + run_resume_hint(shown))
            self.curves.data = curve_data(shown.metrics)
            self.accuracies.data = accuracy_data(shown.metrics)
            scales = curve_scales(shown)
            if self.curves.scales != scales:  # sent only when the run shown changes
                self.curves.scales = scales
                self.accuracies.scales = {**scales, "y": {"auto": False, "range": [0, 1]}}
        finished = [r for r in runs if r.status == FINISHED]
        choices = {f"run-{r.id} ({len(r.env_ids) if r.env_ids else 'train'} envs, {r.settings['iterations']} it.)": r.id
                   for r in reversed(finished)}
        if choices and tuple(self.run_choice.options) != tuple(choices):
            self._run_choices = choices
            self.run_choice.options = tuple(choices)
            self._refresh_checkpoints()

    def _refresh_compare(self) -> None:
        if self.compare_ids is None:
            latest = [e for e in self.jobs.db.evaluations() if e.baseline_id is not None]
            if not latest:
                return
            self.compare_ids = (latest[-1].baseline_id, latest[-1].id)
        before, after = self.compare_ids
        try:
            evaluation = self.jobs.db.evaluation(after)
            c = self.jobs.compare(before, after)
            run = self.jobs.db.run(evaluation.run_id) if evaluation is not None and evaluation.run_id else None
            self.compare.content = compare_html(c, evaluation, run)
        except RunnerError as err:
            self.compare.content = error_html(html.escape(str(err)))
            return
        envs = tuple(str(r["env_id"]) for r in c["episodes"]) or ("(none yet)",)
        if tuple(self.compare_env.options) != envs:
            self.compare_env.options = envs

    def _fill_preset(self) -> None:
        s = RUN_PRESETS[self.run_preset.value]
        self.run_iterations.value, self.run_nd.value, self.run_m.value = (s.iterations, s.rollouts_per_iteration,
                                                                          s.dataset_size)
        self.run_beta0.value, self.run_lr.value, self.run_mirror.value = s.beta0, s.learning_rate, s.mirror

    def _span_iterations(self) -> None:
        if not self.jobs.db.runs():  # the empty chart spans the iterations planned
            scales = curve_scales(None, int(self.run_iterations.value))
            self.curves.scales = scales
            self.accuracies.scales = {**scales, "y": {"auto": False, "range": [0, 1]}}
