"""What the browser page's UI threads are told (`app.page.viewer`, `app.page.jobs_view`): one small frozen record per
kind of event, put on a tab's queue by the runner's thread (what the simulator did), the job manager (a job changed),
viser's callbacks (what a person did) and command answers, and dispatched by type."""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass

from app.live.commands import Grounding, WorldShown
from app.live.recording import Episode


class Event:
    """Any event on the viewer's queue."""


# -- from the runner --------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class WorldChanged(Event):
    shown: WorldShown
    forced: bool = False  # a new tab's first world: shown whatever its origin, unless a link opened one before


@dataclass(frozen=True, eq=False)
class EpisodeStarted(Event):
    episode: Episode
    opened: bool = False  # this tab opened it (a kept episode, a link, a new tab's live one): shown whatever its origin


@dataclass(frozen=True, eq=False)
class StepRecorded(Event):
    episode: Episode


@dataclass(frozen=True, eq=False)
class EpisodeEnded(Event):
    episode: Episode


@dataclass(frozen=True, eq=False)
class StateChanged(Event):
    """The episode was paused or resumed."""

    episode: Episode | None


@dataclass(frozen=True)
class SpeedChanged(Event):
    """The simulator's pace was set (in any tab, or in code with SetSpeed)."""

    steps_per_second: float | None


# -- answers to commands the page posted --------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ShowAnswered(Event):
    """The runner answered a ShowEnv."""

    future: Future


@dataclass(frozen=True, eq=False)
class StartAnswered(Event):
    """The runner answered a StartEpisode (queued it, or refused it)."""

    future: Future


@dataclass(frozen=True, eq=False)
class Grounded(Event):
    """A what-if instruction's grounding at a step, which arrived after the step was drawn without it."""

    key: tuple[int, int, str]  # (episode id, step, instruction)
    result: Grounding | str  # the grounding, or why there is none


# -- from a person ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CursorMoved(Event):
    """The timeline slider was moved to a step."""

    step: int


@dataclass(frozen=True)
class FollowSet(Event):
    follow: bool


@dataclass(frozen=True)
class WatchLive(Event):
    """'Watch it' was pressed: show the episode flying now."""


@dataclass(frozen=True)
class WatchSet(Event):
    """The "Show episodes started elsewhere" box was toggled."""


@dataclass(frozen=True)
class PlaybackPressed(Event):
    button: str  # the playback button's label


@dataclass(frozen=True)
class WhatIf(Event):
    text: str | None  # the what-if instruction to ground; None: clear it


@dataclass(frozen=True)
class GroundClicked(Event):
    """A point of the ground was clicked: inspect its map cell."""

    x: float
    y: float


@dataclass(frozen=True)
class OptionsChanged(Event):
    """A display option changed: redraw."""


@dataclass(frozen=True)
class TaskVisibility(Event):
    """The 'show the task' box was toggled."""


@dataclass(frozen=True)
class Close(Event):
    """The viewer is closing: stop the UI thread."""


@dataclass(frozen=True, eq=False)
class SidesTyped(Event):
    """A typed instruction names a landmark (world, instruction): draw its four sides; None clears them. `typed`:
    something is typed (a goal drawn that is not the typed instruction's then says so)."""

    sides: tuple | None
    typed: bool = False


# -- the Failures and Fine-tune tabs (`app.page.jobs_view`) ---------------------------------------------------------
@dataclass(frozen=True)
class JobChanged(Event):
    """A job started, progressed or ended (`app.jobs.manager.JobManager.listeners`): refresh from the record."""

    kind: str
    job_id: int


@dataclass(frozen=True)
class Pressed(Event):
    """A button of a group was pressed: `control` names the group (eval, run, run_action, compare_replay, page),
    `button` its label."""

    control: str
    button: str


@dataclass(frozen=True)
class ImportAsked(Event):
    path: str


@dataclass(frozen=True)
class EvaluationChosen(Event):
    """Another evaluation was picked in the failure browser."""


@dataclass(frozen=True)
class FiltersChanged(Event):
    """A filter or the sort order of the failure browser changed."""


@dataclass(frozen=True)
class RowPressed(Event):
    row: int  # on the page shown


@dataclass(frozen=True, eq=False)
class Replayed(Event):
    """A replay of an evaluation's episode ended in the live view."""

    episode: Episode


@dataclass(frozen=True, eq=False)
class ReplayRefused(Event):
    row: object  # app.jobs.db.EpisodeRow
    message: str


@dataclass(frozen=True)
class PresetChosen(Event):
    """Another fine-tuning preset was picked: fill its settings in."""


@dataclass(frozen=True)
class IterationsChanged(Event):
    """The planned iterations changed: the empty curves span them."""


# -- the Analysis tab (`app.page.analysis_view`) --------------------------------------------------------------------
@dataclass(frozen=True)
class AnalysisAsked(Event):
    """Analyse the evaluation picked (against the other picked, if any)."""


@dataclass(frozen=True)
class AnalysisViewChanged(Event):
    """Another attribute or confusion matrix was picked: redraw the analysis shown."""


@dataclass(frozen=True)
class Picked(Event):
    """A bar, cell or row of the analysis was clicked: what it counts (app.render.analysis_panels.pick, as typed)."""

    value: str


@dataclass(frozen=True)
class AnalysisRowPressed(Event):
    row: int  # on the page of the episodes shown
