"""The page's "Failures" and "Fine-tune" tabs (viser) of one browser tab: their controls
(`app.page.failures_view`, `app.page.finetune_view`), one queue of typed events (`app.page.events`) and the UI
thread that drains it.

The jobs themselves run in their own processes (`app.jobs.manager`); this view only posts requests to the JobManager
and reads the database. Job events and clicks go into one queue that a UI thread drains, redrawing at most twice a
second, so a running job never slows the live view. What the tabs say is `app.render.jobs_panels`' (pure functions).
"""

from __future__ import annotations

import contextlib
import html
import logging
import math
import queue
import threading
import time
import traceback

import viser
import viser.uplot

from app.jobs.db import EpisodeRow
from app.jobs.manager import JobManager
from app.live.commands import RunnerListener
from app.live.recording import Episode
from app.page.analysis_view import AnalysisTab
from app.page.controls import EXPERT_CHOICE
from app.page.events import (
    AnalysisAsked,
    AnalysisRowPressed,
    AnalysisViewChanged,
    Close,
    EvaluationChosen,
    Event,
    FiltersChanged,
    ImportAsked,
    IterationsChanged,
    JobChanged,
    Picked,
    PresetChosen,
    Pressed,
    Replayed,
    ReplayRefused,
    RowPressed,
)
from app.page.failures_view import ROWS, FailuresTab
from app.page.finetune_view import FinetuneTab
from app.render.jobs_panels import (
    episode_html,
    evaluation_label,
)
from app.render.panels import error_html

log = logging.getLogger("gsmn.dashboard")

REFRESH_SECONDS = 0.5


class JobsView(FailuresTab, FinetuneTab, AnalysisTab, RunnerListener):
    """One tab's Failures, Fine-tune and Analysis tabs: one queue of typed events (`app.page.events`), one UI thread."""

    def __init__(self, viewer, jobs: JobManager):
        self.viewer, self.jobs = viewer, jobs
        self.client: viser.ClientHandle = viewer.client
        self.runner = viewer.runner
        self._events: queue.Queue = queue.Queue()
        self._closing = False
        self.evaluation_id: int | None = None  # the evaluation browsed
        self.rows: list[EpisodeRow] = []  # the episodes the filters select
        self.page = 0
        self.selected: EpisodeRow | None = None
        self.replays: dict[int, tuple[int, int]] = {}  # live episode id -> (evaluation id, env id)
        self.replay_note = ""
        self.replay_detail, self.replay_step = None, None  # where the replay's progress shows; its step to show
        self.compare_ids: tuple[int, int] | None = None  # (before, after) shown side by side
        self._choices: dict[str, int] = {}
        self._run_choices: dict[str, int] = {}
        self._selected_failures: list[int] = []  # the failures the browser's filters select, for a run
        self._build()
        self._on_job = lambda kind, job_id: self._events.put(JobChanged(kind, job_id))
        jobs.listeners.append(self._on_job)
        self.runner.listeners.append(self)
        self.thread = threading.Thread(target=self._loop, name="gsmn-jobs-view", daemon=True)
        self.thread.start()
        self._events.put(JobChanged("start", 0))

    def close(self) -> None:
        self._closing = True
        for listeners, listener in ((self.jobs.listeners, self._on_job), (self.runner.listeners, self)):
            with contextlib.suppress(ValueError):
                listeners.remove(listener)
        self._events.put(Close())
        self.thread.join(timeout=5)

    def on_episode_end(self, episode: Episode) -> None:
        if episode.id in self.replays:
            self._events.put(Replayed(episode))

    def _build(self) -> None:
        gui, panel = self.client.gui, self.viewer.panel
        self._build_failures(gui, panel)
        self._build_finetune(gui, panel)
        self._build_analysis(gui, panel)
        self._connect()

    def _connect(self) -> None:
        """What each control does: put a typed event on the queue (viser's thread pool)."""
        put = self._events.put
        self.eval_buttons.on_click(lambda e: put(Pressed("eval", e.target.value)))
        self.import_button.on_click(lambda _: put(ImportAsked(self.import_path.value.strip())))
        self.evaluation.on_update(lambda e: e.client is not None and put(EvaluationChosen()))
        for control in (self.failed_only, self.landmark, self.side, self.ambiguous, self.stage, self.region,
                        self.sort):
            control.on_update(lambda e: e.client is not None and put(FiltersChanged()))
        for k, button in enumerate(self.row_buttons):
            button.on_click(lambda _, k=k: put(RowPressed(k)))
        self.pager.on_click(lambda e: put(Pressed("page", e.target.value)))
        self.download.on_click(lambda e: put(Pressed("download", e.target.value)))
        self.rescue.on_click(lambda e: put(Pressed("rescue", e.target.value)))
        for box in (self.eval_episodes, self.eval_ids):
            box.on_update(lambda e: e.client is not None and put(Pressed("estimate", "")))
        self.run_preset.on_update(lambda e: e.client is not None and put(PresetChosen()))
        self.run_buttons.on_click(lambda e: put(Pressed("run", e.target.value)))
        self.run_actions.on_click(lambda e: put(Pressed("run_action", e.target.value)))
        self.compare_replay.on_click(lambda e: put(Pressed("compare_replay", e.target.value)))
        self.run_iterations.on_update(lambda e: e.client is not None and put(IterationsChanged()))
        self.an_button.on_click(lambda _: put(AnalysisAsked()))
        for control in (self.an_attribute, self.an_matrix):
            control.on_update(lambda e: e.client is not None and put(AnalysisViewChanged()))
        self.pick_field.on_update(lambda e: e.client is not None and put(Picked(self.pick_field.value)))
        for k, button in enumerate(self.an_rows):
            button.on_click(lambda _, k=k: put(AnalysisRowPressed(k)))
        self.an_pager.on_click(lambda e: put(Pressed("analysis_page", e.target.value)))

    def _checkpoint_choices(self, expert: bool) -> tuple[str, ...]:
        choices = tuple(c for c in self.viewer._policy_choices(first_person=True) if c != EXPERT_CHOICE)
        if expert:
            choices += (EXPERT_CHOICE,)
        return choices or ("(no checkpoint)",)

    def _loop(self) -> None:
        last = 0.0
        pending = False
        while not self._closing:
            events = []
            try:
                events.append(self._events.get(timeout=REFRESH_SECONDS))
                while True:
                    events.append(self._events.get_nowait())
            except queue.Empty:
                pass
            try:
                for event in events:
                    if isinstance(event, Close):
                        return
                    if isinstance(event, JobChanged):
                        pending = True
                    else:
                        self._apply(event)
                if pending and time.monotonic() - last >= REFRESH_SECONDS:
                    self._refresh()
                    pending, last = False, time.monotonic()
            except Exception:  # noqa: BLE001 - keep the page alive; the log says what broke
                log.error("jobs view update failed:\n%s", traceback.format_exc())

    def _apply(self, event: Event) -> None:
        match event:
            case Pressed("eval", button):
                {"Evaluate": self._evaluate, "Cancel": self._cancel_evaluation,
                 "Resume": self._resume_evaluation}[button]()
            case ImportAsked(path):
                self._import(path)
            case EvaluationChosen():
                self.evaluation_id = self._choices.get(self.evaluation.value)
                self.page, self.selected = 0, None
                self._refresh_browser(reset_filters=True)
            case FiltersChanged():
                self.page = 0
                self._refresh_browser()
            case Pressed("page", button):
                pages = max(1, math.ceil(len(self.rows) / ROWS))
                self.page = max(0, min(pages - 1, self.page + (1 if button == "Next" else -1)))
                self._show_rows()
            case Pressed("estimate", _):
                self._show_estimate()
            case Pressed("download", fmt):
                self._download(fmt)
            case Pressed("rescue", stage):
                self._rescue(stage)
            case RowPressed(k):
                if self.page * ROWS + k < len(self.rows):
                    self._replay(self.rows[self.page * ROWS + k])
            case Replayed(episode):
                self._replayed(episode)
            case ReplayRefused(row, message):
                self.replay_detail.content = episode_html(row, error_html(f"Not replayed: {html.escape(message)}"))
            case PresetChosen():
                self._fill_preset()
                self._show_run_estimate(self.jobs.db.runs())
            case Pressed("run", button):
                {"Launch": self._launch, "Cancel": self._cancel_run, "Resume": self._resume_run}[button]()
            case Pressed("run_action", button):
                self._run_action(button)
            case Pressed("compare_replay", button):
                self._compare_replay(button)
            case IterationsChanged():
                self._span_iterations()
                self._show_run_estimate(self.jobs.db.runs())
            case AnalysisAsked():
                self._analyse()
            case AnalysisViewChanged():
                self._show_analysis()
            case Picked(value):
                self._picked(value)
            case AnalysisRowPressed(k):
                self._replay_analysed(k)
            case Pressed("analysis_page", button):
                self._page_analysis(button)

    def _refresh(self) -> None:
        evaluations = self.jobs.db.evaluations()
        runs = self.jobs.db.runs()
        self._choices = {evaluation_label(e): e.id for e in reversed(evaluations)}
        options = tuple(self._choices) or ("(none yet)",)
        if self.evaluation_id is None and evaluations:
            self.evaluation_id = evaluations[-1].id
        if tuple(self.evaluation.options) != options:
            self.evaluation.options = options
        label = next((k for k, v in self._choices.items() if v == self.evaluation_id), None)
        if label is not None and self.evaluation.value != label:
            self.evaluation.value = label
        self._refresh_browser()
        self._refresh_evaluation_status(evaluations)
        self._refresh_runs(runs)
        self._refresh_compare()
        self._refresh_analysable(evaluations)

    def _refresh_checkpoints(self) -> None:
        """Finished runs are checkpoints to switch to: in the Episode panel's policy list and here."""
        policy = self.viewer._policy_choices()
        if tuple(self.viewer.policy.options) != policy:
            value = self.viewer.policy.value
            self.viewer.policy.options = policy
            if value in policy:
                self.viewer.policy.value = value
        for dropdown, expert in ((self.eval_checkpoint, True), (self.run_checkpoint, False)):
            choices = self._checkpoint_choices(expert)
            if tuple(dropdown.options) != choices:
                value = dropdown.value
                dropdown.options = choices
                if value in choices:
                    dropdown.value = value
