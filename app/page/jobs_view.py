"""The page's "Failures" and "Fine-tune" tabs (viser): evaluate a checkpoint, browse its episodes with their
failure attribution, replay one in the live view with one click, launch DAggerFM on the failures selected, watch
its progress and curves, cancel it, fly its checkpoint, and rerun the same episodes before/after side by side.

The jobs themselves run in their own processes (`app.jobs.manager`); this view only posts requests to the JobManager and
reads the database. Job events and clicks go into one queue that a UI thread drains, redrawing at most twice a
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

from app.api.jobs import replay_policy
from app.jobs.db import ACTIVE, FAILED, FINISHED, EpisodeRow, Evaluation, Run
from app.jobs.manager import JobManager
from app.jobs.settings import RUN_PRESETS, run_settings
from app.live.commands import RunnerError, RunnerListener, StartEpisode
from app.live.recording import Episode
from app.render.jobs_panels import (
    CURVE_AXES,
    CURVE_SERIES,
    SETTING_HINTS,
    SORTS,
    accuracy_data,
    compare_html,
    curve_data,
    curve_scales,
    episode_colour,
    episode_html,
    episode_label,
    error_summary,
    evaluation_label,
    note_html,
    resume_hint,
    run_resume_hint,
    runs_html,
    short_path,
    sort_rows,
    stage_title,
    summary_html,
)
from app.render.panels import error_html
from gsmn.attribution import PIPELINE, reported_stages
from gsmn.evaluation import parse_env_ids
from gsmn.world.spec import SPLITS

log = logging.getLogger("gsmn.dashboard")

ROWS = 12  # episode buttons per page of the failure browser
REGION_CHOICES = {"flew through it": True, "never entered": False}  # the "Success region" filter
ALL = "all"
EXPERT_CHOICE = "Expert (oracle)"
ENV_TRAIN = "train split"
REFRESH_SECONDS = 0.5


class JobsView(RunnerListener):
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
        self.compare_ids: tuple[int, int] | None = None  # (before, after) shown side by side
        self._choices: dict[str, int] = {}
        self._run_choices: dict[str, int] = {}
        self._selected_failures: list[int] = []  # the failures the browser's filters select, for a run
        self._build()
        self._on_job = lambda kind, job_id: self._events.put(("job", kind, job_id))
        jobs.listeners.append(self._on_job)
        self.runner.listeners.append(self)
        self.thread = threading.Thread(target=self._loop, name="gsmn-jobs-view", daemon=True)
        self.thread.start()
        self._events.put(("job", "start", 0))

    def close(self) -> None:
        self._closing = True
        for listeners, listener in ((self.jobs.listeners, self._on_job), (self.runner.listeners, self)):
            with contextlib.suppress(ValueError):
                listeners.remove(listener)
        self._events.put(("close",))
        self.thread.join(timeout=5)

    # -- runner events (runner thread: only enqueue) ----------------------------------------------------------
    def on_episode_end(self, episode: Episode) -> None:
        if episode.id in self.replays:
            self._events.put(("replayed", episode))

    # -- the GUI ----------------------------------------------------------------------------------------------
    def _build(self) -> None:
        gui, panel = self.client.gui, self.viewer.panel
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
        with panel.add_tab("Fine-tune", viser.Icon.SCHOOL):
            with gui.add_folder("DAggerFM from a checkpoint"):
                self.run_checkpoint = gui.add_dropdown("Start from", self._checkpoint_choices(expert=False))
                self.run_preset = gui.add_dropdown("Preset", tuple(RUN_PRESETS), initial_value="tiny",
                                                   hint="tiny: a minute or two here; small: tens of minutes; paper: "
                                                        "the original's 150 iterations")
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

        self.eval_buttons.on_click(lambda e: self._events.put(("eval", e.target.value)))
        self.import_button.on_click(lambda _: self._events.put(("import", self.import_path.value.strip())))
        self.evaluation.on_update(lambda e: e.client is not None and self._events.put(("browse",)))
        for control in (self.failed_only, self.landmark, self.side, self.ambiguous, self.stage, self.region,
                        self.sort):
            control.on_update(lambda e: e.client is not None and self._events.put(("filter",)))
        for k, button in enumerate(self.row_buttons):
            button.on_click(lambda _, k=k: self._events.put(("row", k)))
        self.pager.on_click(lambda e: self._events.put(("page", e.target.value)))
        self.run_preset.on_update(lambda e: e.client is not None and self._events.put(("preset",)))
        self.run_buttons.on_click(lambda e: self._events.put(("run", e.target.value)))
        self.run_actions.on_click(lambda e: self._events.put(("run_action", e.target.value)))
        self.compare_replay.on_click(lambda e: self._events.put(("compare_replay", e.target.value)))
        self.run_iterations.on_update(lambda e: e.client is not None and self._events.put(("iterations",)))

    def _checkpoint_choices(self, expert: bool) -> tuple[str, ...]:
        choices = tuple(c for c in self.viewer._policy_choices() if c != EXPERT_CHOICE)
        if expert:
            choices += (EXPERT_CHOICE,)
        return choices or ("(no checkpoint)",)

    # -- the UI thread ----------------------------------------------------------------------------------------
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
                    if event[0] == "close":
                        return
                    if event[0] == "job":
                        pending = True
                    else:
                        self._apply(event)
                if pending and time.monotonic() - last >= REFRESH_SECONDS:
                    self._refresh()
                    pending, last = False, time.monotonic()
            except Exception:  # noqa: BLE001 - keep the page alive; the log says what broke
                log.error("jobs view update failed:\n%s", traceback.format_exc())

    def _apply(self, event: tuple) -> None:
        kind = event[0]
        if kind == "eval":
            {"Evaluate": self._evaluate, "Cancel": self._cancel_evaluation,
             "Resume": self._resume_evaluation}[event[1]]()
        elif kind == "import":
            self._import(event[1])
        elif kind == "browse":
            self.evaluation_id = self._choices.get(self.evaluation.value)
            self.page, self.selected = 0, None
            self._refresh_browser(reset_filters=True)
        elif kind == "filter":
            self.page = 0
            self._refresh_browser()
        elif kind == "page":
            pages = max(1, math.ceil(len(self.rows) / ROWS))
            self.page = max(0, min(pages - 1, self.page + (1 if event[1] == "Next" else -1)))
            self._show_rows()
        elif kind == "row":
            k = self.page * ROWS + event[1]
            if k < len(self.rows):
                self._replay(self.rows[k])
        elif kind == "replayed":
            self._replayed(event[1])
        elif kind == "replay_failed":
            self.detail.content = episode_html(event[1], error_html(f"Not replayed: {html.escape(event[2])}"))
        elif kind == "preset":
            s = RUN_PRESETS[self.run_preset.value]
            self.run_iterations.value, self.run_nd.value, self.run_m.value = (s.iterations, s.rollouts_per_iteration,
                                                                              s.dataset_size)
            self.run_beta0.value, self.run_lr.value, self.run_mirror.value = s.beta0, s.learning_rate, s.mirror
        elif kind == "run":
            {"Launch": self._launch, "Cancel": self._cancel_run, "Resume": self._resume_run}[event[1]]()
        elif kind == "run_action":
            self._run_action(event[1])
        elif kind == "compare_replay":
            self._compare_replay(event[1])
        elif kind == "iterations" and not self.jobs.db.runs():  # the empty chart spans the iterations planned
            scales = curve_scales(None, int(self.run_iterations.value))
            self.curves.scales = scales
            self.accuracies.scales = {**scales, "y": {"auto": False, "range": [0, 1]}}

    # -- evaluations -------------------------------------------------------------------------------------------
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

    # -- the failure browser -----------------------------------------------------------------------------------
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
        self.summary.content = summary_html(e, counts, self.jobs.db.region_counts(e.id))
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
        pages = max(1, math.ceil(n / ROWS))
        self.page = min(self.page, pages - 1)
        shown = self.rows[self.page * ROWS:(self.page + 1) * ROWS]
        for k, button in enumerate(self.row_buttons):
            if k < len(shown):
                button.label = episode_label(shown[k])
                button.color = episode_colour(shown[k])
                button.visible = True
            else:
                button.visible = False
        self.list_note.content = (f"**{n}** episode{'s' if n != 1 else ''} match; page {self.page + 1} of {pages}. "
                                  "Click one to fly it again in the live view." if n else "No episode matches.")

    def _replay(self, row: EpisodeRow) -> None:
        self.selected = row
        e = self.jobs.db.evaluation(row.evaluation_id)
        try:
            policy, checkpoint = replay_policy(e)
        except RunnerError as err:
            self.detail.content = episode_html(row, error_html(html.escape(str(err))))
            return
        self.replay_note = "Flying it again in the live view..."
        self.detail.content = episode_html(row, self.replay_note)
        future = self.runner.post(StartEpisode(row.env_id, None, policy, checkpoint, preempt=True,
                                                origin=self.viewer.origin))

        def started(f, row=row) -> None:
            try:
                self.replays[f.result().id] = (row.evaluation_id, row.env_id)
            except Exception as err:  # noqa: BLE001 - shown to the user
                self._events.put(("replay_failed", row, str(err)))

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
                       f"it differs from the evaluation ({episode.result.steps} steps, ended {gap:.2f} m away): the "
                       f"server's settings differ from the evaluation's."))
        self.detail.content = episode_html(row, note)

    # -- runs --------------------------------------------------------------------------------------------------
    def _launch(self) -> None:
        choice = self.run_checkpoint.value
        checkpoint = self.viewer.checkpoint_of(choice)
        env_ids = None
        if self.run_envs.value != ENV_TRAIN:
            env_ids = list(self._selected_failures)
        try:
            settings = run_settings(self.run_preset.value, iterations=int(self.run_iterations.value),
                                    rollouts_per_iteration=int(self.run_nd.value), dataset_size=int(self.run_m.value),
                                    beta0=float(self.run_beta0.value), learning_rate=float(self.run_lr.value),
                                    mirror=float(self.run_mirror.value))
            r = self.jobs.start_run(settings, checkpoint, env_ids or None,
                                    self.evaluation_id if env_ids else None)
        except (RunnerError, ValueError) as err:
            self.run_status.content = error_html(f"**Not started:** {html.escape(str(err))}")
            return
        where = f"{len(env_ids)} failures of evaluation {self.evaluation_id}" if env_ids else "the train split"
        self.run_status.content = f"Run {r.id} started from {html.escape(short_path(r.init_checkpoint))} on {where}."
        self._refresh()

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
            return
        baseline = run.source_evaluation_id or self.evaluation_id
        if baseline is None:
            self.run_note.content = error_html("No evaluation to compare with: evaluate a checkpoint first.")
            return
        before = self.jobs.db.evaluation(baseline)
        try:  # flown the way the evaluation it reruns was (plain or as a mirror ensemble)
            e = self.jobs.start_evaluation(run.checkpoint, None, baseline_id=baseline, run_id=run.id,
                                           mirror_ensemble=bool(before and before.mirror_ensemble))
        except RunnerError as err:
            self.run_note.content = error_html(f"**Not started:** {html.escape(str(err))}")
            return
        self.compare_ids = (baseline, e.id)
        self.run_note.content = f"Evaluation {e.id} reruns the episodes of evaluation {baseline} with run-{run.id}."
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

    # -- refreshing from the database --------------------------------------------------------------------------
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

    def _refresh_evaluation_status(self, evaluations: list[Evaluation]) -> None:
        active = [e for e in evaluations if e.status in ACTIVE]
        if active:
            e = active[-1]
            self.eval_progress.visible = True
            self.eval_progress.value = 100.0 * e.done / max(1, e.total)
            self.eval_status.content = f"Evaluation {e.id} ({html.escape(e.label)}): {e.done} of {e.total} episodes."
        elif evaluations and self.eval_progress.visible:
            e = evaluations[-1]
            self.eval_progress.visible = False
            where = f" at {e.done} of {e.total} episodes (Resume: in the failure browser)" if resume_hint(e) else ""
            self.eval_status.content = f"Evaluation {e.id} {e.status}{where}." + (
                f" {html.escape(error_summary(e.error))}" if e.status == "failed" else "")

    def _refresh_runs(self, runs: list[Run]) -> None:
        self.runs_table.content = runs_html(runs)
        active = [r for r in runs if r.status in ACTIVE]
        shown = active[-1] if active else (runs[-1] if runs else None)
        if shown is not None:
            p = shown.progress or {}
            self.run_progress.visible = shown.status in ACTIVE
            self.run_progress.value = 100.0 * float(p.get("fraction", 0.0))
            text = html.escape(p.get("text", "starting"))
            if shown.status in ACTIVE:
                self.run_status.content = f"**Run {shown.id}** (running): {text}."
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
