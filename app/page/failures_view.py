"""The page's "Failures" tab (viser; the tab's jobs UI thread, `app.page.jobs_view`): evaluate a checkpoint, browse
its episodes with their failure attribution, and replay one in the live view with one click. What the tab says is
`app.render.jobs_panels`' (pure functions).
"""

from __future__ import annotations

import html
import math
import time

import viser
import viser.uplot

from app.jobs.db import ACTIVE, EpisodeRow, Evaluation
from app.jobs.evaluation_export import export_evaluation, export_name
from app.jobs.results import evaluation_camera, look_words, replay_intervention, replay_policy, rescue_of
from app.live.commands import RunnerError, StartEpisode
from app.live.recording import Episode
from app.page.controls import EXPERT_CHOICE
from app.page.events import CursorMoved, ReplayRefused
from app.page.finetune_view import ENV_TRAIN
from app.render.estimates import evaluation_estimate, evaluation_remaining
from app.render.jobs_panels import (
    SORTS,
    episode_colour,
    episode_hint,
    episode_html,
    episode_label,
    error_summary,
    note_html,
    rescue_html,
    resume_hint,
    sort_rows,
    stage_title,
    summary_html,
)
from app.render.panels import error_html
from gsmn.attribution import PIPELINE, reported_stages
from gsmn.evaluation import parse_env_ids
from gsmn.world.spec import SPLITS

ROWS = 12  # episode buttons per page of the failure browser
RESCUES = {"perception": "truth-semantic", "grounding": "truth-relevance", "goal": "truth-goal"}
REGION_CHOICES = {"flew through it": True, "never entered": False}  # the "Success region" filter
ALL = "all"


def show_page(buttons, rows: list[EpisodeRow], page: int) -> tuple[int, int]:
    """Episode buttons showing page `page` of `rows` (kept within the pages there are), the others hidden; the page
    shown and how many there are."""
    pages = max(1, math.ceil(len(rows) / len(buttons)))
    page = min(page, pages - 1)
    shown = rows[page * len(buttons):(page + 1) * len(buttons)]
    for k, button in enumerate(buttons):
        if k < len(shown):
            button.label, button.hint = episode_label(shown[k]), episode_hint(shown[k])
            button.color, button.visible = episode_colour(shown[k]), True
        else:
            button.visible = False
    return page, pages


class FailuresTab:
    """The Failures tab's part of `app.page.jobs_view.JobsView` (its controls are attributes of the view)."""

    def _build_failures(self, gui, panel) -> None:
        with panel.add_tab("Failures", viser.Icon.BUG):
            with gui.add_folder("Evaluate a checkpoint"):
                self.eval_checkpoint = gui.add_dropdown("Checkpoint", self._checkpoint_choices(expert=True))
                self.eval_split = gui.add_dropdown("Split", SPLITS, initial_value="test")
                self.eval_episodes = gui.add_number("Episodes", 30, min=1, max=5000, step=1,
                                                    hint="the split's first this many environments")
                self.eval_ids = gui.add_text("Or env ids", "", hint="'70:80' or '70,73,81': instead of the split")
                self.eval_mirror = gui.add_checkbox("As mirror ensemble", False,
                                                    hint="the model also flies the mirror image of each step and the "
                                                         "two actions are averaged (twice the compute; not in the "
                                                         "paper); replays fly the same way")
                self.eval_buttons = gui.add_button_group("Evaluation", ("Evaluate", "Cancel", "Resume"))
                self.eval_estimate = gui.add_markdown("")
                self.eval_progress = gui.add_progress_bar(0.0, visible=False)
                self.eval_status = gui.add_markdown("Evaluations run in their own process; their episodes and "
                                                    "failures appear below as they finish.")
                # loading a file is the rarer way in: folded away, and said to read the server's disk
                with gui.add_folder("Or load a gsmn eval JSON file", expand_by_default=False):
                    gui.add_markdown("A `gsmn eval --json` file **on the server**, inside its data folder (a relative "
                                     "path starts there); it is not uploaded from this browser.")
                    self.import_path = gui.add_text("Path on server", "", hint="e.g. runs/gsmn.json")
                    self.import_button = gui.add_button("Load", icon=viser.Icon.UPLOAD, color="gray")
            with gui.add_folder("Failure browser"):
                self.evaluation = gui.add_dropdown("Evaluation", ("(none yet)",))
                self.summary = gui.add_html("")
                self.download = gui.add_button_group("Download", ("CSV", "JSON"),
                                                     hint="this evaluation's results: one row per episode, with its "
                                                          "split and what flew it (JSON: with the summary)")
                self.rescue = gui.add_button_group(
                    "Rescue with true", tuple(RESCUES), hint="fly this evaluation's failures again from the start "
                    "with that stage's true map in place of the model's own: how many each saves, by the stage "
                    "they are attributed to, shows above (docs/model.md, 'Interventions')")
                self.failed_only = gui.add_checkbox("Failed only", True)
                self.landmark = gui.add_dropdown("Landmark", (ALL,))
                self.side = gui.add_dropdown("Side", (ALL, "left", "right", "front", "back"))
                self.ambiguous = gui.add_dropdown("Ambiguous", (ALL, "ambiguous", "unambiguous"))
                self.stage = gui.add_dropdown("Attributed to", (ALL, *(stage_title(k) for k in PIPELINE)),
                                              hint="the names of the bars above")
                self.region = gui.add_dropdown("Success region", (ALL, *REGION_CHOICES),
                                               hint="whether the drone was ever where a STOP would have succeeded: "
                                                    "a failure that flew through it failed on its STOP")
                self.sort = gui.add_dropdown("Sort by", tuple(SORTS), initial_value="flown order")
                self.list_note = gui.add_markdown("")
                self.row_buttons = [gui.add_button(f"row {k}", visible=False) for k in range(ROWS)]
                self.pager = gui.add_button_group("Page", ("Previous", "Next"))
                self.detail = gui.add_html(note_html("Pick an episode: it flies again in the live view with "
                                                        "its maps, and its attribution shows here."))

    def _download(self, fmt: str) -> None:
        """Send the evaluation picked as a CSV or JSON file to this tab (app.jobs.evaluation_export)."""
        e = self.jobs.db.evaluation(self.evaluation_id) if self.evaluation_id is not None else None
        if e is None:
            self.list_note.content = "No evaluation to download yet: evaluate a checkpoint first."
            return
        fmt = fmt.lower()
        data = export_evaluation(self.jobs.db, e, fmt)
        self.client.send_file_download(export_name(e, fmt), data, save_immediately=True)
        held = len(self.jobs.db.episodes(e.id))
        self.list_note.content = (f"Downloaded {export_name(e, fmt)}: {held} episode{'s' if held != 1 else ''}"
                                  + ("." if e.status == "finished" else f" of {e.total} ({e.status})."))

    def _rescue(self, stage: str) -> None:
        """Start the evaluation that flies the failures shown with a truth map intervention (`rescue_failures`)."""
        if self.evaluation_id is None:
            self.list_note.content = "No evaluation yet: evaluate a checkpoint first."
            return
        try:
            e = self.jobs.rescue_failures(self.evaluation_id, RESCUES[stage])
        except RunnerError as err:
            self.list_note.content = f"**Not started:** {html.escape(str(err))}"
            return
        self.list_note.content = f"Evaluation {e.id} started: {html.escape(e.label)}."
        self._refresh()

    def _rescue_table(self, e: Evaluation) -> str:
        """The rescue table of `e`'s failures (`app.jobs.results.rescue_of`), or "" when none was flown."""
        if e.intervention:
            return ""
        table = rescue_of(self.jobs.db, e)
        return rescue_html(table, table["running"]) if table["evaluations"] else ""

    def _evaluate(self) -> None:
        choice = self.eval_checkpoint.value
        system, checkpoint = ("oracle", None) if choice == EXPERT_CHOICE else (None, self.viewer.checkpoint_of(choice))
        try:
            ids = parse_env_ids(self.eval_ids.value.strip()) if self.eval_ids.value.strip() else None
            e = self.jobs.start_evaluation(checkpoint, system, None if ids else self.eval_split.value,
                                           None if ids else int(self.eval_episodes.value), ids,
                                           mirror_ensemble=bool(self.eval_mirror.value) and system != "oracle")
        except (RunnerError, ValueError) as err:
            self.eval_status.content = error_html(f"**Not started:** {html.escape(str(err))}")
            return
        self.evaluation_id = e.id
        self.eval_status.content = f"Evaluation {e.id} started: {html.escape(e.label)}."
        self._refresh()

    def _cancel_evaluation(self) -> None:
        active = self.jobs.db.evaluations(ACTIVE)
        if not active:
            self.eval_status.content = "No evaluation is running."
            return
        try:
            self.jobs.cancel_evaluation(active[-1].id)
        except RunnerError as err:
            self.eval_status.content = error_html(html.escape(str(err)))

    def _resume_evaluation(self) -> None:
        """Fly the rest of the evaluation shown in the failure browser, if it was cancelled or failed."""
        if self.evaluation_id is None:
            self.eval_status.content = "No evaluation to resume yet."
            return
        try:
            self.jobs.resume_evaluation(self.evaluation_id)
        except RunnerError as err:
            self.eval_status.content = error_html(f"**Not resumed:** {html.escape(str(err))}")
            return
        self._refresh()  # its progress line: the kept episodes count as done

    def _import(self, path: str) -> None:
        if not path:
            self.eval_status.content = error_html("Type the path of a `gsmn eval --json` file first.")
            return
        try:
            e = self.jobs.import_evaluation(path)
        except RunnerError as err:
            self.eval_status.content = error_html(f"**Not loaded:** {html.escape(str(err))}")
            return
        self.evaluation_id = e.id
        self.eval_status.content = f"Loaded {html.escape(path)} as evaluation {e.id} ({e.total} episodes)."
        self._refresh()

    def _refresh_browser(self, reset_filters: bool = False) -> None:
        e = self.jobs.db.evaluation(self.evaluation_id) if self.evaluation_id else None
        if e is None:
            self.summary.content = note_html("No evaluation yet: evaluate a checkpoint above.")
            self.rows = []
            self._show_rows()
            return
        every = self.jobs.db.episodes(e.id)
        landmarks = (ALL, *sorted({r.landmark for r in every}))
        if tuple(self.landmark.options) != landmarks:
            keep = self.landmark.value if self.landmark.value in landmarks and not reset_filters else ALL
            self.landmark.options = landmarks
            self.landmark.value = keep
        counts = self.jobs.db.stage_counts(e.id)
        self.summary.content = summary_html(e, counts, self.jobs.db.region_counts(e.id)) + self._rescue_table(e)
        stage_of_title = {stage_title(k): k for k in reported_stages(counts)}  # the stages the bars show
        if tuple(self.stage.options) != (ALL, *stage_of_title):
            keep = self.stage.value if self.stage.value in stage_of_title and not reset_filters else ALL
            self.stage.options = (ALL, *stage_of_title)
            self.stage.value = keep
        ambiguous = {"ambiguous": True, "unambiguous": False}.get(self.ambiguous.value)
        self.rows = self.jobs.db.episodes(
            e.id, failed_only=bool(self.failed_only.value),
            landmark=None if self.landmark.value == ALL else self.landmark.value,
            side=None if self.side.value == ALL else self.side.value, ambiguous=ambiguous,
            stage=stage_of_title.get(self.stage.value),
            entered_region=REGION_CHOICES.get(self.region.value))
        self.rows = sort_rows(self.rows, self.sort.value)
        self._show_rows()
        failures = [r.env_id for r in self.rows if not r.success]
        label = f"failures selected in the browser ({len(failures)})"
        options = (ENV_TRAIN, label) if failures else (ENV_TRAIN,)
        if tuple(self.run_envs.options) != options:
            chose_train = len(self.run_envs.options) > 1 and self.run_envs.value == ENV_TRAIN  # keep that choice
            self.run_envs.options = options
            self.run_envs.value = ENV_TRAIN if chose_train or not failures else label
        self._selected_failures = failures

    def _show_rows(self) -> None:
        n = len(self.rows)
        self.page, pages = show_page(self.row_buttons, self.rows, self.page)
        self.list_note.content = (f"**{n}** episode{'s' if n != 1 else ''} match; page {self.page + 1} of {pages}. "
                                  "Click one to fly it again in the live view." if n else "No episode matches.")

    def _replay(self, row: EpisodeRow, detail=None, step: int | None = None) -> None:
        """Fly an evaluated episode again in the live view, telling `detail` (default: the failure browser's) how
        it goes; once it ends, the timeline moves to `step` (where the analysis says it went wrong), if given."""
        self.selected, self.replay_detail, self.replay_step = row, detail or self.detail, step
        e = self.jobs.db.evaluation(row.evaluation_id)
        try:
            policy, checkpoint = replay_policy(e)
        except RunnerError as err:
            self.replay_detail.content = episode_html(row, error_html(html.escape(str(err))))
            return
        self.replay_note = "Flying it again in the live view..." + (
            f" The timeline then shows step {step}, where it went wrong." if step is not None else "")
        self.replay_detail.content = episode_html(row, self.replay_note)
        future = self.runner.post(StartEpisode(row.env_id, None, policy, checkpoint, preempt=True,
                                                origin=self.viewer.origin, intervention=replay_intervention(e)))

        def started(f, row=row) -> None:
            try:
                self.replays[f.result().id] = (row.evaluation_id, row.env_id)
            except Exception as err:  # noqa: BLE001 - shown to the user
                self._events.put(ReplayRefused(row, str(err)))

        future.add_done_callback(started)

    def _replayed(self, episode: Episode) -> None:
        evaluation_id, env_id = self.replays.pop(episode.id)
        row = self.jobs.db.episode(evaluation_id, env_id)
        if row is None or self.selected is None or (self.selected.evaluation_id, self.selected.env_id) != (
                evaluation_id, env_id):
            return
        if episode.result is None:
            note = f"The replay {episode.status} after {len(episode.steps)} steps."
        else:
            gap = math.hypot(episode.result.final_x - row.final_x, episode.result.final_y - row.final_y)
            same = gap < 0.01 and episode.result.steps == row.steps
            note = (f"Replayed as episode {episode.id}: "
                    + ("it reproduces the evaluation (same steps, final position within 1 cm). Scrub the timeline to "
                       "see its maps at any step." if same else
                       f"it differs from the evaluation ({episode.result.steps} steps, ended {gap:.2f} m away): "
                       + self._replay_difference(evaluation_id)))
            if self.replay_step is not None and same:
                self.viewer._events.put(CursorMoved(self.replay_step))
                note += f" Shown at step {self.replay_step}, where it went wrong."
            elif self.replay_step is not None:
                note += f" It went wrong at step {self.replay_step} of the evaluation's flight, not of this one."
        self.replay_detail.content = episode_html(row, note)

    def _replay_difference(self, evaluation_id: int) -> str:
        """Why a replay may not reproduce an evaluation's episode: the look of its images, when that differs."""
        flown = evaluation_camera(self.jobs.db.evaluation(evaluation_id))
        if flown is not None and look_words(flown) != look_words(self.runner.config.camera):
            return (f"the evaluation's images were drawn with {look_words(flown)}, the live view's with "
                    f"{look_words(self.runner.config.camera)}, so the model may fly it differently.")
        return "the server's settings differ from the evaluation's."

    def _chosen_episodes(self) -> int | None:
        """How many episodes the form would evaluate (None while its ids do not parse)."""
        try:
            text = self.eval_ids.value.strip()
            return len(parse_env_ids(text)) if text else int(self.eval_episodes.value)
        except ValueError:
            return None

    def _show_estimate(self, evaluations: list[Evaluation] | None = None) -> None:
        """Before an evaluation: how long the one in the form would take here (app.render.estimates), from the
        record's `evaluations` (read when not given)."""
        n = self._chosen_episodes()
        evaluations = self.jobs.db.evaluations() if evaluations is None else evaluations
        if n is not None and not any(e.status in ACTIVE for e in evaluations):
            self.eval_estimate.content = f"*{evaluation_estimate(n, evaluations)}*"

    def _refresh_evaluation_status(self, evaluations: list[Evaluation]) -> None:
        active = [e for e in evaluations if e.status in ACTIVE]
        self._show_estimate(evaluations)
        if active:
            e = active[-1]
            self.eval_progress.visible = True
            self.eval_progress.value = 100.0 * e.done / max(1, e.total)
            left = evaluation_remaining(e, time.time(), evaluations)
            self.eval_status.content = (f"Evaluation {e.id} ({html.escape(e.label)}): {e.done} of {e.total} "
                                        f"episodes{f', {left}' if left else ''}.")
        elif evaluations and self.eval_progress.visible:
            e = evaluations[-1]
            self.eval_progress.visible = False
            where = f" at {e.done} of {e.total} episodes (Resume: in the failure browser)" if resume_hint(e) else ""
            self.eval_status.content = f"Evaluation {e.id} {e.status}{where}." + (
                f" {html.escape(error_summary(e.error))}" if e.status == "failed" else "")
