"""The browser page (viser): controls on the left, the 3D scene in the middle, camera and maps on the right.

Every action goes to the runner as a command (`app.live.runner`), the same commands the HTTP API posts. What the
runner reports (a world shown, an episode started, a step recorded, an episode ended) and what a person does go
into this viewer's event queue as typed records (`app.page.events`); one UI thread turns events into scene and GUI
updates, drawing only the newest step when the simulator is ahead of the page, so a slow browser never slows the
simulator. The timeline shows any recorded
step of the displayed episode, live or finished, with every view (scene, camera, maps, readouts) in sync.

**A view per tab.** Every browser tab (viser client) has its own Viewer: its own controls, scene, timeline, episode
shown, counterfactual and layers (viser's client-level GUI and scene handles), so one tab scrubbing, replaying or
showing another world never moves another's. Shared on purpose, and said so on the page: the simulator (one episode
flies at a time; Run, Pause, Step, Stop and Speed act on it for every tab) and the jobs. Commands carry the tab's
`origin`, and so do the episodes and worlds they make: a tab shows its own worlds only, its own episodes, and
episodes started elsewhere (other tabs, the API) while its "Show episodes started elsewhere" box is ticked (unticked
in a new tab, which starts on the server's world; opening a kept episode or a link unticks it, and so does presenter
mode). An episode flying that the tab does not show is said under the status line, with a "Watch episode N" button.
"""

from __future__ import annotations

import contextlib
import html
import logging
import queue
import threading
import time
import traceback
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np
import viser
import viser.uplot

from app.live.commands import (
    Cancel,
    Grounding,
    Pause,
    Resume,
    RunnerError,
    RunnerListener,
    ShowEnv,
    StepOnce,
    WorldShown,
)
from app.live.recording import Episode, StepRecord, jpeg_bytes
from app.live.runner import Runner
from app.page.controls import WATCH_LABEL, ViewerControls, speed_choice
from app.page.drawing import ViewerDrawing
from app.page.events import (
    Close,
    CursorMoved,
    EpisodeEnded,
    EpisodeStarted,
    Event,
    FollowSet,
    GroundClicked,
    Grounded,
    OptionsChanged,
    PlaybackPressed,
    ShowAnswered,
    SidesTyped,
    SpeedChanged,
    StartAnswered,
    StateChanged,
    StepRecorded,
    TaskVisibility,
    WatchLive,
    WatchSet,
    WhatIf,
    WorldChanged,
)
from app.page.scene import CAMERA_FAR, CAMERA_NEAR, DEFAULT_CAMERA, SceneView
from app.render.panels import (
    camera_html,
    error_html,
    other_side,
    placeholder_html,
    status_line,
    world_summary,
)
from gsmn.model.grid import world_cell

log = logging.getLogger("gsmn.dashboard")

REPLAY_STEPS_PER_SECOND = 10.0
# A live episode is drawn at most this often, whatever the simulator's pace: each drawn step costs the page a 3D
# redraw, and a browser on the same cores would take that time from the simulator (docs/dashboard.md).
LIVE_FRAMES_PER_SECOND = 10.0


@dataclass
class _View:
    """What the page shows (owned by the UI thread)."""

    episode: Episode | None = None
    cursor: int = 0
    follow: bool = True
    replaying: bool = False
    counterfactual: str | None = None  # the what-if instruction while that mode is on
    inspected: tuple[float, float] | None = None  # a ground point clicked to inspect its map cell
    plot_steps: tuple[int, int] = (-1, -1)  # (steps, cursor) in the plot, to redraw it only when either moves


def configure_server(server: viser.ViserServer) -> None:
    """What every tab shares from the start: +z up, and the first camera over the field from beyond its
    south-west corner (viser applies the initial camera when a client connects, before its Viewer exists)."""
    server.scene.set_up_direction("+z")
    camera = server.initial_camera
    camera.position, camera.look_at, camera.up, camera.fov = (DEFAULT_CAMERA[k] for k in (
        "position", "look_at", "up", "fov"))
    camera.near, camera.far = CAMERA_NEAR, CAMERA_FAR

class Viewer(ViewerControls, ViewerDrawing, RunnerListener):
    """One browser tab's page. `client`: its viser ClientHandle (its own `gui`, `scene` and `atomic()`)."""

    def __init__(self, client: viser.ClientHandle, runner: Runner, env_id: int = 70):
        self.client = client
        self.origin = f"tab-{client.client_id}"  # on the commands this tab posts (app.live.commands.Command.origin)
        self.runner = runner
        self._checkpoint_of_choice: dict[str, str] = {}  # a policy menu entry ("Model: <label>") -> checkpoint name
        cam = runner.config.camera
        from gsmn.world.assets import load_catalogue

        self.scene = SceneView(client, load_catalogue(), runner.config.task.success_radius, cam.vfov_deg,
                               cam.width / cam.height)
        self.view = _View()
        self.world_shown: WorldShown | None = None
        self._events: queue.Queue = queue.Queue()
        self._grounded: dict[tuple[int, int, str], Grounding | str] = {}
        self._grounding: set[tuple[int, int, str]] = set()
        self._closing = False
        self._last_replay = 0.0
        self.rng = np.random.default_rng()
        self._marks: tuple = ()
        self._clicked_at: float | None = None
        self.click_to_frame: list[float] = []  # s from a Run click to its first frame sent, for the benchmark
        self._whatif_at: float | None = None
        self.whatif_to_frame: list[float] = []  # s from a Ground click to the what-if maps sent
        self.frames_drawn = 0  # steps drawn, and the time it took (for the benchmark)
        self.render_seconds = 0.0
        field, cells = runner.config.world.field_size, runner.config.model.map_size
        self._cell_of = lambda x, y: world_cell(x, y, field, cells)
        self._elsewhere_id: int | None = None  # the episode flying elsewhere that this tab does not show
        self._watch_target: int | None = None  # the episode "Watch episode N" names, kept once it lands
        self._env_timer = None  # shows a typed environment id's world once the typing pauses (app.page.controls)
        self._last_run = 0.0  # when Run was last pressed (perf_counter)
        self._build_controls(env_id)
        self._build_views()
        runner.listeners.append(self)
        self._events.put(SpeedChanged(runner.speed))  # the pace may have changed since the box was built
        self.thread = threading.Thread(target=self._loop, name=f"gsmn-viewer-{client.client_id}", daemon=True)
        self.thread.start()
        # a new tab starts on its own: the server's world, not the world or episode another tab shows (one flying
        # is said under the status line, with a button to watch it); asked with no origin, so no other tab takes it
        shown = runner.shown
        if shown is not None and shown.world.env_id == env_id:
            self._events.put(WorldChanged(shown, forced=True))
        else:
            runner.post(ShowEnv(env_id)).add_done_callback(
                lambda f: f.exception() is None and self._events.put(WorldChanged(f.result(), forced=True)))

    def close(self) -> None:
        """The tab went: stop listening to the runner and end the UI thread."""
        self._closing = True
        if self._env_timer is not None:
            self._env_timer.cancel()
        with contextlib.suppress(ValueError):
            self.runner.listeners.remove(self)
        self._events.put(Close())
        self.thread.join(timeout=5)

    def watching(self) -> bool:
        """Whether this tab shows the episodes and worlds started elsewhere (other tabs, the API)."""
        return bool(self.watch_others.value)

    # -- runner events (runner thread: only enqueue) ------------------------------------------------------------
    def on_world(self, shown: WorldShown) -> None:
        self._events.put(WorldChanged(shown))

    def on_episode_start(self, episode: Episode) -> None:
        self._events.put(EpisodeStarted(episode))

    def on_step(self, episode: Episode, record: StepRecord) -> None:
        self._events.put(StepRecorded(episode))

    def on_episode_end(self, episode: Episode) -> None:
        self._events.put(EpisodeEnded(episode))

    def on_state(self, episode: Episode | None, paused: bool) -> None:
        self._events.put(StateChanged(episode))

    def on_speed(self, steps_per_second: float | None) -> None:
        self._events.put(SpeedChanged(steps_per_second))

    # -- the UI thread ----------------------------------------------------------------------------------------
    def _loop(self) -> None:
        """Apply events and draw. A live episode's new steps are drawn at most LIVE_FRAMES_PER_SECOND times a
        second (its first step at once); anything a person does is drawn at once."""
        frame_due: float | None = None  # when the newest live step is to be drawn
        last_frame = 0.0
        while not self._closing:
            timeout = 1.0 / REPLAY_STEPS_PER_SECOND if self.view.replaying else 1.0
            if frame_due is not None:
                timeout = min(timeout, max(0.0, frame_due - time.perf_counter()))
            events: list[Event] = []
            try:
                events.append(self._events.get(timeout=timeout))
                while True:
                    events.append(self._events.get_nowait())
            except queue.Empty:
                pass
            try:
                draw_now = False
                for event in events:
                    if isinstance(event, Close):
                        return
                    dirty = self._apply(event)
                    if dirty and isinstance(event, StepRecorded) and len(event.episode.steps) > 1:
                        if frame_due is None:
                            frame_due = last_frame + 1.0 / LIVE_FRAMES_PER_SECOND
                    else:
                        draw_now |= dirty
                draw_now |= self._replay_tick()
                if draw_now or (frame_due is not None and time.perf_counter() >= frame_due):
                    frame_due, last_frame = None, time.perf_counter()
                    self._render()
            except Exception:  # noqa: BLE001 - keep the page alive; the log says what broke
                log.error("viewer update failed:\n%s", traceback.format_exc())

    def _apply(self, event: Event) -> bool:
        """Apply one event to the view (the reducer); True when the shown step must be redrawn."""
        v = self.view
        match event:
            case WorldChanged(shown, forced):  # not another tab's; a new tab's first unless it shows one already
                if (forced and v.episode is None and self.world_shown is None) or shown.origin == self.origin:
                    self._show_world(shown)
                return False
            case EpisodeStarted(episode, opened):
                return self._episode_started(episode, opened)
            case WatchLive():  # the button: its episode even if it landed while the click was on its way
                return self._watch_live(landed_too=True)
            case WatchSet():  # ticked: the episode flying now shows at once
                return self.watching() and self._watch_live()
            case StepRecorded(episode):
                return self._step_recorded(episode)
            case EpisodeEnded(episode):
                return self._episode_ended(episode)
            case StateChanged(episode):
                if episode is v.episode and v.episode is not None:
                    self.status.content = status_line(v.episode)
                return False
            case SpeedChanged(steps_per_second):
                return self._show_speed(steps_per_second)
            case CursorMoved(step):
                return self._move_cursor(step)
            case FollowSet(follow):
                v.follow = follow
                if v.follow and v.episode is not None and v.episode.steps:
                    v.cursor = len(v.episode.steps) - 1
                return True
            case PlaybackPressed(button):
                return self._playback(button)
            case ShowAnswered(future) | StartAnswered(future):
                return self._command_answered(future, started=isinstance(event, StartAnswered))
            case WhatIf(text):
                return self._set_counterfactual(text)
            case Grounded(key, result):
                self._grounding.discard(key)
                self._grounded[key] = result
                return v.episode is not None and key[:2] == (v.episode.id, v.cursor)
            case OptionsChanged():
                return True
            case GroundClicked(x, y):
                v.inspected = (x, y)
                return True
            case SidesTyped(sides, typed):
                with self.client.atomic():
                    self.scene.draw_sides(*sides) if sides else self.scene.draw_sides(None)
                    self.scene.label_goal(sides[1] if sides else None, typed)
                return False
            case TaskVisibility():
                with self.client.atomic():
                    self.scene.set_task_visible(bool(self.show_task.value))
                return False
        return False

    def _episode_started(self, episode: Episode, opened: bool) -> bool:
        if not (opened or episode.origin == self.origin or self.watching()):
            self._started_elsewhere(episode)
            return False
        if not opened and self.compare.keeps_shown(episode):
            return False
        self._start(episode)
        return False

    def _step_recorded(self, episode: Episode) -> bool:
        v = self.view
        if episode is v.episode:
            if v.follow:
                v.cursor = len(episode.steps) - 1
            return v.follow or len(episode.steps) <= 2  # the timeline grows either way
        return v.follow and self.compare.is_partner(episode)

    def _episode_ended(self, episode: Episode) -> bool:
        v = self.view
        if episode.id == self._elsewhere_id:
            self._started_elsewhere(None)
        if episode is not v.episode:
            return self.compare.is_partner(episode)
        v.cursor = len(episode.steps) - 1 if v.follow else v.cursor
        self.show_result(episode)
        self.status.content = status_line(episode)
        return True

    def _show_speed(self, steps_per_second: float | None) -> bool:
        shown = speed_choice(steps_per_second)
        options = self._speed_options(shown)
        if self.speed.value != shown or tuple(self.speed.options) != options:
            with self.client.atomic():
                self.speed.options = options
                self.speed.value = shown
        return False

    def _move_cursor(self, step: int) -> bool:
        v = self.view
        if v.episode is not None and v.episode.steps:
            v.cursor = max(0, min(step, len(v.episode.steps) - 1))
            v.follow = v.cursor == len(v.episode.steps) - 1 and v.episode.live
            v.replaying = False
            self.follow.value = v.follow
        return True

    def _command_answered(self, future: Future, started: bool) -> bool:
        try:
            result = future.result()
        except RunnerError as e:  # said once, in the status line; the result below is labelled with its episode
            shown = self.view.episode
            still = f" Still shown: episode {shown.id} and its result." if shown is not None and started else ""
            self.status.content = error_html(f"**Not started:** {html.escape(str(e))}{still}")
            if started:
                self.instruction_note.content = ""
            return False
        except Exception as e:  # noqa: BLE001
            self.status.content = f"**Error:** {html.escape(str(e))}"
            return False
        if started:
            self.instruction_note.content = ""
            self.status.content = f"Episode {result.id} queued."
        return False

    def _show_world(self, shown: WorldShown) -> None:
        self.world_shown = shown
        v = self.view
        v.episode, v.cursor, v.follow, v.replaying = None, 0, True, False
        with self.client.atomic():
            if self.scene.world != shown.world:
                self.scene.draw_world(shown.world, self._on_ground_click, self._on_landmark_click)
                self.forget_cell()
            self.scene.clear_layers()
            self.scene.clear_path()
            self.scene.draw_counterfactual(None)
            self.compare.clear()
            task = shown.task
            self.scene.draw_task(task.instruction if task else None, task.path if task else None)
            self.scene.set_drone(shown.position, shown.yaw, shown.T_world_camera, shown.image)
        self.camera.content = camera_html(jpeg_bytes(shown.image))
        world = shown.world
        with self.client.atomic():
            self.scene.draw_sides(None)
        self.env_number.value = str(world.env_id)
        self.split.value = world.split
        if task is not None:
            self.instruction.value = task.instruction.text
            self.whatif.value = other_side(task.instruction.text, task.instruction.side)
        self.instruction_note.content = ""
        self._set_chips(self.instruction.value, world)
        self.run_button.color = "green"
        self.status.content = f"**Environment {world.env_id}** ({world.split}): {world_summary(world)}. Press **Run**."
        self.result.content = ""
        self.readout.content = f"Step 0 of environment {world.env_id}, at the start corner."
        self.maps.content = placeholder_html("Run an episode to see the model's maps, live at every step.")
        self._set_timeline(0, 0)
        live = self.runner.live
        if live is not None:  # still flying, unseen here (this tab's own, or another's): say so, with a way back
            self._started_elsewhere(live)

    def _watch_live(self, landed_too: bool = False) -> bool:
        """Show the episode flying now, at its newest step (`landed_too`: else the one the button named, landed
        since, at its end); False when there is none or it is shown already."""
        live = self.runner.live
        if live is None and landed_too and self._watch_target is not None:
            live = self.runner.episodes.get(self._watch_target)
        if live is None or live is self.view.episode:
            return False
        self._start(live)
        self.view.cursor = max(0, len(live.steps) - 1)
        return live.live or self._episode_ended(live)

    def _started_elsewhere(self, episode: Episode | None) -> None:
        """Say (or stop saying) that an episode flies that this tab does not show (another tab's, the API's, or its
        own left for a world), with a button to watch it."""
        self._elsewhere_id = episode.id if episode is not None else None
        if episode is None:
            self.elsewhere.visible = self.watch_live.visible = False
            return
        if episode.origin == self.origin:
            where = "started here and still flying"
        else:
            where = "flying, started " + ("over the API" if episode.origin is None else "in another tab")
        self.elsewhere.content = (f"<small>Episode {episode.id} is {where}: one simulator flies for every tab. "
                                  f"*Watch it* shows it here; so does ticking **{WATCH_LABEL}** (Playback) for every "
                                  "new one.</small>")
        self._watch_target = episode.id
        self.watch_live.label = f"Watch episode {episode.id}"
        self.elsewhere.visible = self.watch_live.visible = True

    def _start(self, episode: Episode) -> None:
        if episode.id == self._elsewhere_id:
            self._started_elsewhere(None)
        v = self.view
        v.episode, v.cursor, v.follow, v.replaying, v.plot_steps = episode, 0, True, False, (-1, -1)
        self.compare.reset_plot()
        self.follow.value = True
        world = episode.task.world
        self.world_shown = None
        with self.client.atomic():
            if self.scene.world != world:
                self.scene.draw_world(world, self._on_ground_click, self._on_landmark_click)
                self.forget_cell()
            self.scene.clear_path()
            self.scene.draw_task(episode.task.instruction, episode.task.path)
            self.scene.draw_counterfactual(None)
        if v.counterfactual is not None:
            self._draw_counterfactual_task(episode, v.counterfactual)
        self.env_number.value = str(world.env_id)
        self.split.value = world.split
        self.instruction.value = episode.instruction
        self.instruction_note.content = ""
        self._set_chips(episode.instruction, world)
        self.run_button.color = "green"
        with self.client.atomic():
            self.scene.draw_sides(None)
        if v.counterfactual is None:
            self.whatif.value = other_side(episode.instruction, episode.task.instruction.side)
        self.result.content = ""
        self.status.content = status_line(episode)

    def _playback(self, button: str) -> bool:
        v, episode = self.view, self.view.episode
        live = episode is not None and episode.live
        if button == "Play":
            if live:
                self.runner.post(Resume())
                v.follow = True
                self.follow.value = True
            elif episode is not None and episode.steps:
                if v.cursor >= len(episode.steps) - 1:
                    v.cursor = 0
                v.replaying = True
                self._last_replay = time.perf_counter()
                return True
            else:
                self._run(paused=False)
        elif button == "Pause":
            if live:
                self.runner.post(Pause())
            v.replaying = False
        elif button == "Step":
            if live:
                self.runner.post(StepOnce())
                v.follow = True
                self.follow.value = True
            elif episode is not None and episode.steps:
                v.replaying = False
                v.cursor = min(v.cursor + 1, len(episode.steps) - 1)
                return True
            else:
                self._run(paused=True)
        elif button == "Stop":
            v.replaying = False
            if live:
                self.runner.post(Cancel())
        return False

    def _replay_tick(self) -> bool:
        v = self.view
        if not v.replaying or v.episode is None:
            return False
        now = time.perf_counter()
        if now - self._last_replay < 1.0 / REPLAY_STEPS_PER_SECOND:
            return False
        self._last_replay = now
        if v.cursor >= len(v.episode.steps) - 1:
            v.replaying = False
            return False
        v.cursor += 1
        return True
