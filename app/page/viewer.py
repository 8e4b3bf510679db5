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
episodes started elsewhere (other tabs, the API) while its "Show episodes started elsewhere" box is ticked (the
default; opening a kept episode or a link unticks it, and so does presenter mode). An episode flying that the tab
does not show is said under the status line, with a "Watch episode N" button.
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
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass

import numpy as np
import viser
import viser.uplot
from viser._messages import GuiSliderMark

from app.live.commands import (
    Cancel,
    Ground,
    Grounding,
    Pause,
    Resume,
    RunnerError,
    RunnerListener,
    SetSpeed,
    ShowEnv,
    StartEpisode,
    StepOnce,
    WorldShown,
)
from app.live.recording import Episode, StepRecord, jpeg_bytes
from app.live.runner import Runner
from app.page.compare_view import CompareView
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
from app.render.layers import LAYERS, RANGE_MODES, VALUE_MODES, frame_of, inspect_cell, map_layers, map_title
from app.render.panels import (
    ACTIONS_AXES,
    ACTIONS_SCALES,
    ACTIONS_SERIES,
    actions_data,
    camera_html,
    compose_instruction,
    error_html,
    inspector_markdown,
    maps_html,
    other_side,
    parse_env_id,
    placeholder_html,
    readout_markdown,
    result_markdown,
    side_help,
    status_line,
    suggestions,
    timeline_marks,
    whatif_markdown,
    which_landmark,
    world_summary,
)
from app.render.truth import result_rows
from gsmn.model.grid import world_cell
from gsmn.task.instructions import SIDES, InstructionError, parse_instruction
from gsmn.task.understand import understand
from gsmn.world.spec import SPLITS, split_env_ids, split_of, world_for_env

log = logging.getLogger("gsmn.dashboard")

EXPERT_CHOICE = "Expert (oracle)"
SPEEDS = {"as fast as it goes": None, "real time (5 steps/s)": 5.0, "2x (10 steps/s)": 10.0,
          "slow (2 steps/s)": 2.0}
REPLAY_STEPS_PER_SECOND = 10.0
# A live episode is drawn at most this often, whatever the simulator's pace: each drawn step costs the page a 3D
# redraw, and a browser on the same cores would take that time from the simulator (docs/dashboard.md).
LIVE_FRAMES_PER_SECOND = 10.0
FOLLOW_LABEL = "Follow the live step"
WATCH_LABEL = "Show episodes started elsewhere"
SHARED_NOTE = ("<small>This tab has its own timeline, episode, counterfactual and layers. **Shared by every tab:** "
               "the one simulator (one episode flies at a time: Run, Pause, Step, Stop and Speed act on it for "
               "everyone) and the jobs.</small>")
GROUNDING_WAIT = 0.25  # s the page waits for a counterfactual grounding before drawing without it


def speed_choice(steps_per_second: float | None) -> str:
    """The Speed box's entry for a pace: one of SPEEDS, or the figure itself."""
    for label, value in SPEEDS.items():
        if value == steps_per_second:
            return label
    return f"{steps_per_second:g} steps/s"  # set in code (SetSpeed), not one of the choices


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


class Viewer(RunnerListener):
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
        self._build_controls(env_id)
        self._build_views()
        runner.listeners.append(self)
        self._events.put(SpeedChanged(runner.speed))  # the pace may have changed since the box was built
        self.thread = threading.Thread(target=self._loop, name=f"gsmn-viewer-{client.client_id}", daemon=True)
        self.thread.start()
        # what a new tab shows first: the episode flying now, else the world shown last, else its own
        live, shown = runner.live, runner.shown
        if live is not None:
            self._events.put(EpisodeStarted(live, opened=True))
        elif shown is not None:
            self._events.put(WorldChanged(shown, forced=True))
        else:
            self._post(ShowEnv(env_id), ShowAnswered)

    def close(self) -> None:
        """The tab went: stop listening to the runner and end the UI thread."""
        self._closing = True
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

    # -- the GUI ----------------------------------------------------------------------------------------------
    def _build_controls(self, env_id: int) -> None:
        gui = self.client.gui
        gui.configure_theme(dark_mode=False, show_logo=False, brand_color=(40, 110, 245))
        gui.main_panel.dock_left()
        gui.main_panel.set_width(330)
        self.intro = gui.add_markdown("**GSMN dashboard**: follow an instruction with the Grounded Semantic Mapping "
                                      "Network (Blukis et al., RSS 2018) and watch what it maps, grounds and plans.")
        self.checkpoint_note = gui.add_markdown(self._checkpoint_text())

        with gui.add_folder("Episode"):
            # a text box, not a number box: the browser's number box turns "-5" or "abc" silently into 0
            self.env_number = gui.add_text("Environment id", str(env_id),
                                           hint="a whole number; id % 100: 0-69 train, 70-84 test, 85-99 dev")
            self.split = gui.add_dropdown("Split", SPLITS, initial_value=split_of(env_id))
            self.env_buttons = gui.add_button_group("World", ("Show", "Random in split"))
            choices = self._policy_choices()
            self._default_choice = choices[0]
            self.policy = gui.add_dropdown("Policy", choices, initial_value=choices[0],
                                           hint="the expert flies with the model watching, when there is one")
            self.mirror = gui.add_checkbox("Mirror ensemble", False,
                                           hint="the model also flies the mirror image of each step (left and right "
                                                "swapped) and the two actions are averaged; the maps shown are the "
                                                "unmirrored copy's")
            # no hover hint: it covered the row above; the note under the box and the word chips help instead
            self.instruction = gui.add_text("Instruction", "")
            self.instruction_note = gui.add_markdown("")
            # the template's words and this world's landmark names, as buttons that fill the instruction in
            self.side_chips = gui.add_button_group("Sides", SIDES)
            self.name_chips = gui.add_button_group("Landmarks", ("(none)",))
            self.run_button = gui.add_button("Run", color="green", icon=viser.Icon.PLAYER_PLAY,
                                              hint="fly this instruction in this world from the start")
            self.status = gui.add_markdown("")
            self.elsewhere = gui.add_markdown("", visible=False)  # an episode flying that this tab does not show
            self.watch_live = gui.add_button("Watch it", icon=viser.Icon.EYE, visible=False,
                                             hint="show the episode flying now in this tab")
            # the result right under the status: on a 1280 x 800 screen it shows without scrolling
            self.result = gui.add_markdown("")
        with gui.add_folder("Playback"):
            self.playback = gui.add_button_group("Control", ("Play", "Pause", "Step", "Stop"))
            self.timeline = gui.add_slider("Step", min=0, max=1, step=1, initial_value=0)
            self.follow = gui.add_checkbox(FOLLOW_LABEL, True)
            self.watch_others = gui.add_checkbox(WATCH_LABEL, True,
                                                 hint="episodes flown from other tabs or the API appear here as "
                                                      "they start; untick to keep this tab on its own")
            speed = speed_choice(self.runner.speed)
            self.speed = gui.add_dropdown("Speed", self._speed_options(speed), initial_value=speed,
                                          hint="the simulator's pace, for every tab")
            self.shared_note = gui.add_markdown(SHARED_NOTE)
        with gui.add_folder("Counterfactual: another instruction, same map"):
            self.whatif = gui.add_text("What if", "", hint="grounded on the semantic map at the shown step")
            self.whatif_buttons = gui.add_button_group("Ground", ("Ground", "Clear"))
            self.whatif_note = gui.add_markdown("Type another instruction: its relevance and goal maps and the action "
                                                "it would give appear at once, on the map already built.")
        self.compare = CompareView(self)  # comparisons, forks and the ground truth (app.page.compare_view)
        self.compare.build_controls(gui)
        with gui.add_folder("Layers on the ground", expand_by_default=True):
            # the world-frame layers of the model's output record (app.render.layers.LAYERS), the goal map shown first
            labels = {"semantic": ("Semantic map", False), "relevance": ("Relevance map", False),
                      "goal": ("Goal map", True)}
            self.layer_boxes = {name: gui.add_checkbox(*labels.get(name, (map_title(name), False)))
                                for name in LAYERS if name in labels or frame_of(name) == "world"}
            self.opacity = gui.add_slider("Opacity", min=0.0, max=1.0, step=0.05, initial_value=0.8)
            self.value_mode = gui.add_dropdown("Map values", VALUE_MODES, initial_value="probability",
                                               hint="probability: the model's auxiliary heads; raw: channel 0")
            self.range_mode = gui.add_dropdown("Colour range", RANGE_MODES, initial_value="fixed",
                                               hint="fixed: 0 to 1 for probabilities; frame: each frame's min to max")
            self.show_task = gui.add_checkbox("Goal, success region, paths", True)

        self.env_buttons.on_click(self._on_env_button)
        self.run_button.on_click(lambda _: self._run(paused=False))
        self.env_number.on_update(self._on_env_typed)
        self.side_chips.on_click(lambda e: self._fill_instruction(side=e.target.value))
        self.name_chips.on_click(lambda e: self._fill_instruction(name=e.target.value))
        self.policy.on_update(lambda _: self._on_policy())
        self.whatif.on_update(self._on_whatif_typed)
        self.instruction.on_update(self._on_instruction_typed)
        self.playback.on_click(self._on_playback)
        self.timeline.on_update(self._on_timeline)
        self.follow.on_update(self._on_follow)
        self.watch_others.on_update(lambda e: self._events.put(WatchSet()) if e.client is not None else None)
        self.watch_live.on_click(lambda _: self._events.put(WatchLive()))
        self.speed.on_update(self._on_speed)
        self.whatif_buttons.on_click(self._on_whatif)
        for box in self.layer_boxes.values():
            box.on_update(lambda _: self._events.put(OptionsChanged()))
        for control in (self.opacity, self.value_mode, self.range_mode):
            control.on_update(lambda _: self._events.put(OptionsChanged()))
        self.show_task.on_update(lambda _: self._events.put(TaskVisibility()))

    def _build_views(self) -> None:
        gui = self.client.gui
        panel = gui.add_panel()
        with panel.add_tab("Camera and maps", viser.Icon.MAP):
            gui.add_markdown("Camera")
            self.camera = gui.add_html(camera_html(jpeg_bytes(np.zeros((144, 256, 3), np.uint8))))
            self.readout = gui.add_markdown("")
            self.maps = gui.add_html(placeholder_html("Run an episode to see the model's maps."))
            self.inspector = gui.add_markdown("Click the field in the 3D view to inspect a map cell.")
        with panel.add_tab("Actions", viser.Icon.CHART_LINE):
            self.plot = gui.add_uplot(
                data=tuple(np.zeros(2) for _ in ACTIONS_SERIES), series=ACTIONS_SERIES,
                title="Actions flown, P(stop), the shown step", aspect=1.3, scales=ACTIONS_SCALES,
                axes=ACTIONS_AXES)
            gui.add_markdown("The black line follows the timeline; green: the steps inside the success region, where "
                             "a STOP would have succeeded; the model stops when P(stop) passes 0.5. The model's own v "
                             "and omega are in the readout under the camera when the expert flies.")
            self.compare.build_plot(gui)
        self.compare.build_tab(panel, gui)
        panel.dock_right()
        panel.set_width(420)
        self.panel = panel

    def _checkpoint_text(self) -> str:
        """The header's model line: the policy chosen in the Episode panel when it is not the server's default."""
        if not self.runner.has_model:
            return f"**No model loaded.** {html.escape(self.runner.checkpoint_message)}"
        choice = getattr(self, "policy", None)
        default = getattr(self, "_default_choice", None)
        if choice is None or choice.value == default:
            return f"**Model:** {html.escape(self.runner.checkpoint_message)}"
        if choice.value == EXPERT_CHOICE:
            return (f"**Flies:** the expert, the model watching ({html.escape(self.runner.checkpoint_message)})")
        name = self.checkpoint_of(choice.value)
        return f"**Flies:** checkpoint **{html.escape(str(name))}** (chosen under Policy; the server loaded " \
               f"{html.escape(str(default).removeprefix('Model: '))} at start)."

    def _policy_choices(self) -> tuple[str, ...]:
        choices = []
        for info in self.runner.checkpoint_list():
            if info.kind in ("gsmn", "gsmn-no-plan") and (info.loaded or info.error is None):
                label = f"Model: {info.label or info.name}"
                if label in self._checkpoint_of_choice and self._checkpoint_of_choice[label] != info.name:
                    label = f"Model: {info.name}"  # two checkpoints of one label (a menu of duplicates shows nothing)
                self._checkpoint_of_choice[label] = info.name
                if info.default:
                    choices.insert(0, label)
                else:
                    choices.append(label)
        return (*choices, EXPERT_CHOICE)

    def _policy_of_choice(self) -> tuple[str, str | None]:
        choice = self.policy.value
        if choice == EXPERT_CHOICE:
            return "expert", None
        return ("mirror" if self.mirror.value else "model"), self.checkpoint_of(choice)

    def checkpoint_of(self, choice: str) -> str | None:
        """The checkpoint name of a policy menu entry ("Model: GSMN without J_ground (...)" -> "table2/no-ground");
        None for the expert."""
        if not choice.startswith("Model: "):
            return None
        return self._checkpoint_of_choice.get(choice, choice.removeprefix("Model: "))

    # -- callbacks (viser's thread pool: post commands, enqueue events) -----------------------------------------
    def _on_env_button(self, event: viser.GuiEvent) -> None:
        if event.target.value == "Random in split":
            self.env_number.value = str(split_env_ids(self.split.value, 1,
                                                      start=int(self.rng.integers(0, 100000)))[0])
        env_id = self._env_id()
        if env_id is None:
            return
        self._post(ShowEnv(env_id), ShowAnswered)

    def _env_id(self) -> int | None:
        """The environment id typed, or None with the reason in the status line."""
        try:
            env_id = parse_env_id(self.env_number.value)
        except ValueError as e:
            self.status.content = error_html(f"**Environment id:** {html.escape(str(e))}")
            return None
        return env_id

    def _on_env_typed(self, event: viser.GuiEvent) -> None:
        if event.client is None:
            return
        try:
            env_id = parse_env_id(self.env_number.value)
        except ValueError as e:
            self.status.content = error_html(html.escape(str(e)))
            return
        if self.split.value != split_of(env_id):  # the split always names the id's own
            self.split.value = split_of(env_id)
        self.instruction_note.content = self._instruction_feedback(self.instruction.value)

    def _fill_instruction(self, side: str | None = None, name: str | None = None) -> None:
        """A chip or a landmark clicked in the scene: put that side or landmark into the instruction template."""
        world = self._typed_world()
        if world is None or name == "(none)":
            return
        self.instruction.value = compose_instruction(self.instruction.value, world, side, name)
        self.instruction_note.content = self._instruction_feedback(self.instruction.value)

    def _set_chips(self, text: str, world, understood=None) -> None:
        names = suggestions(text, world, understood) if world is not None else ()
        options = names or ("(none)",)
        if tuple(self.name_chips.options) != options:
            self.name_chips.options = options

    def _on_policy(self) -> None:
        self.checkpoint_note.content = self._checkpoint_text()

    def _run(self, paused: bool) -> None:
        self._clicked_at = time.perf_counter()
        policy, checkpoint = self._policy_of_choice()
        text = self.instruction.value.strip() or None
        env_id = self._env_id()
        if env_id is None:
            return
        self.status.content = "Starting..."
        self._post(StartEpisode(env_id, text, policy, checkpoint, preempt=True, paused=paused), StartAnswered)

    def _post(self, command, answered: type[ShowAnswered | StartAnswered]) -> Future:
        command.origin = self.origin  # what it starts is this tab's
        future = self.runner.post(command)
        future.add_done_callback(lambda f: self._events.put(answered(f)))
        return future

    def _on_instruction_typed(self, event: viser.GuiEvent) -> None:
        if event.client is None:
            return
        self.instruction_note.content = self._instruction_feedback(self.instruction.value)

    def _typed_world(self):
        """The world of the environment id typed (the one shown when it is that one); None for a bad id."""
        try:
            env_id = parse_env_id(self.env_number.value)
        except ValueError:
            return None
        if self.world_shown and self.world_shown.world.env_id == env_id:
            return self.world_shown.world
        episode = self.view.episode
        if episode is not None and episode.task.world.env_id == env_id:
            return episode.task.world
        return world_for_env(env_id, self.runner.config.world)

    def _instruction_feedback(self, text: str) -> str:
        """The note under the instruction box (checked as it is typed), the word chips under it, the Run button's
        colour (green only when it can be flown) and the sides drawn around the landmark named."""
        world = self._typed_world()
        understood = understand(text, world) if world is not None else None  # read once: note and chips
        self._set_chips(text, world, understood)
        if not text.strip():
            self._can_fly(True, None)
            return "Empty: the environment's own instruction will be flown."
        if world is None:
            self._can_fly(False, None)
            return error_html("**Cannot fly this:** the environment id is not a whole number from 0 up.")
        instruction = understood.instruction
        if instruction is None:
            self._can_fly(False, None)
            if understood.candidates:
                return error_html(f"**Pick one:** {html.escape(understood.reason or '')}. The chips below name them.")
            # the chips below list the world's landmarks: the note gives the reason and two instructions to try
            return error_html(f"**Cannot fly this:** {html.escape(understood.message(tries=2, listing=False))}")
        self._can_fly(True, (world, instruction))
        note = f" ({which_landmark(world, instruction)})" if instruction.ambiguous else ""
        ignored = (f" Ignored: {html.escape(', '.join(understood.ignored))}." if understood.ignored else "")
        return (f"Understood as: **{html.escape(instruction.text)}**{note}.{ignored} " + side_help(world, instruction))

    def _can_fly(self, ok: bool, sides) -> None:
        self.run_button.color = "green" if ok else "gray"
        self._events.put(SidesTyped(sides))

    def _on_playback(self, event: viser.GuiEvent) -> None:
        self._events.put(PlaybackPressed(event.target.value))

    def _on_speed(self, event: viser.GuiEvent) -> None:
        # a person chose (our own updates come with client None); the extra entry of a pace set in code is that pace
        if event.client is not None and self.speed.value in SPEEDS:
            self.runner.post(SetSpeed(SPEEDS[self.speed.value]))

    @staticmethod
    def _speed_options(shown: str) -> tuple[str, ...]:
        return tuple(SPEEDS) if shown in SPEEDS else (*SPEEDS, shown)

    def _on_timeline(self, event: viser.GuiEvent) -> None:
        if event.client is not None:  # a person moved it (our own updates come with client None)
            self._events.put(CursorMoved(int(self.timeline.value)))

    def _on_follow(self, event: viser.GuiEvent) -> None:
        if event.client is not None:
            self._events.put(FollowSet(bool(self.follow.value)))

    def _on_ground_click(self, x: float, y: float) -> None:
        self._events.put(GroundClicked(x, y))

    def _on_landmark_click(self, name: str) -> None:
        """A landmark clicked in the 3D view goes into the instruction (the rest of it kept)."""
        self._fill_instruction(name=name)

    def _on_whatif_typed(self, event: viser.GuiEvent) -> None:
        """The what-if box is checked as it is typed, like the instruction box."""
        if event.client is None:
            return
        text, episode = self.whatif.value.strip(), self.view.episode
        if not text or episode is None:
            return
        understood = understand(text, episode.task.world)
        if understood.instruction is None:
            self.whatif_note.content = error_html(f"**Cannot ground this:** {html.escape(understood.message())}")
            return
        self.whatif_note.content = (f"Understood as: **{html.escape(understood.instruction.text)}**. "
                                    "Press **Ground**.")

    def _on_whatif(self, event: viser.GuiEvent) -> None:
        if event.target.value == "Clear":
            self._events.put(WhatIf(None))
        else:
            self._whatif_at = time.perf_counter()
            self._events.put(WhatIf(self.whatif.value.strip()))

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
        """Apply one event to the view; True when the shown step must be redrawn."""
        v = self.view
        match event:
            case WorldChanged(shown, forced):
                if forced or shown.origin == self.origin:  # another tab's world is its own business
                    self._show_world(shown)
                return False
            case EpisodeStarted(episode, opened):
                if not (opened or episode.origin == self.origin or self.watching()):
                    self._started_elsewhere(episode)
                    return False
                if not opened and self.compare.keeps_shown(episode):
                    return False
                self._start(episode)
                return False
            case WatchLive():
                return self._watch_live()
            case WatchSet():  # ticked: the episode flying now shows at once
                return self.watching() and self._watch_live()
            case StepRecorded(episode):
                if episode is v.episode:
                    if v.follow:
                        v.cursor = len(episode.steps) - 1
                    return v.follow or len(episode.steps) <= 2  # the timeline grows either way
                return v.follow and self.compare.is_partner(episode)
            case EpisodeEnded(episode):
                if episode.id == self._elsewhere_id:
                    self._started_elsewhere(None)
                if episode is v.episode:
                    v.cursor = len(episode.steps) - 1 if v.follow else v.cursor
                    model = self.runner.models.get(episode.checkpoint) if episode.checkpoint else None
                    self.result.content = result_markdown(episode, self.runner.config.task.success_radius) + \
                        result_rows(episode, model.heads if model else None, self.runner.config.task.success_radius)
                    self.status.content = status_line(episode)
                    return True
                return self.compare.is_partner(episode)
            case StateChanged(episode):
                if episode is v.episode and v.episode is not None:
                    self.status.content = status_line(v.episode)
                return False
            case SpeedChanged(steps_per_second):
                shown = speed_choice(steps_per_second)
                options = self._speed_options(shown)
                if self.speed.value != shown or tuple(self.speed.options) != options:
                    with self.client.atomic():
                        self.speed.options = options
                        self.speed.value = shown
                return False
            case CursorMoved(step):
                if v.episode is not None and v.episode.steps:
                    v.cursor = max(0, min(step, len(v.episode.steps) - 1))
                    v.follow = v.cursor == len(v.episode.steps) - 1 and v.episode.live
                    v.replaying = False
                    self.follow.value = v.follow
                return True
            case FollowSet(follow):
                v.follow = follow
                if v.follow and v.episode is not None and v.episode.steps:
                    v.cursor = len(v.episode.steps) - 1
                return True
            case PlaybackPressed(button):
                return self._playback(button)
            case ShowAnswered(future):
                return self._command_answered(future, started=False)
            case StartAnswered(future):
                return self._command_answered(future, started=True)
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
            case SidesTyped(sides):
                with self.client.atomic():
                    if sides:
                        self.scene.draw_sides(*sides)
                    else:
                        self.scene.draw_sides(None)
                return False
            case TaskVisibility():
                with self.client.atomic():
                    self.scene.set_task_visible(bool(self.show_task.value))
                return False
        return False

    def _command_answered(self, future: Future, started: bool) -> bool:
        try:
            result = future.result()
        except RunnerError as e:  # said once, in the status line; the result below is labelled with its episode
            self.status.content = error_html(f"**Not started:** {html.escape(str(e))}")
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
                self.scene.mark_cell(None, 1.0)
                v.inspected = None
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

    def _watch_live(self) -> bool:
        """Show the episode flying now, at its newest step; False when there is none or it is shown already."""
        live = self.runner.live
        if live is None or live is self.view.episode:
            return False
        self._start(live)
        self.view.cursor = max(0, len(live.steps) - 1)
        return True

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
                self.scene.mark_cell(None, 1.0)
                v.inspected = None
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

    # -- counterfactual -----------------------------------------------------------------------------------------
    def _set_counterfactual(self, text: str | None) -> bool:
        v = self.view
        if not text:
            v.counterfactual = None
            with self.client.atomic():
                self.scene.draw_counterfactual(None)
            self.whatif_note.content = "Counterfactual cleared: the maps are the episode's own again."
            return True
        episode = v.episode
        if episode is None or not episode.steps:
            self.whatif_note.content = "Run an episode first: the counterfactual is grounded on its semantic map."
            return False
        if episode.checkpoint is None:
            self.whatif_note.content = ("This episode has no semantic map (no model watched it); load a checkpoint "
                                        "to ground other instructions.")
            return False
        try:
            instruction = parse_instruction(text, episode.task.world)
        except InstructionError as e:  # refused: the previous what-if maps go, so none is left looking valid
            self.whatif_note.content = error_html(f"**Cannot ground this:** {html.escape(str(e))}")
            if v.counterfactual is None:
                return False
            v.counterfactual = None
            with self.client.atomic():
                self.scene.draw_counterfactual(None)
            return True
        v.counterfactual = instruction.text
        self._draw_counterfactual_task(episode, instruction.text)
        return True

    def _draw_counterfactual_task(self, episode: Episode, text: str) -> None:
        try:
            instruction = parse_instruction(text, episode.task.world)
        except InstructionError:
            return
        with self.client.atomic():
            self.scene.draw_counterfactual(instruction)

    def _counterfactual_at(self, episode: Episode, step: int) -> Grounding | str | None:
        """The grounding of the what-if instruction at this step: cached, or requested (None until it comes)."""
        text = self.view.counterfactual
        if text is None or episode.checkpoint is None:
            return None
        key = (episode.id, step, text)
        if key in self._grounded:
            return self._grounded[key]
        if key in self._grounding:
            return None
        if len(self._grounded) > 300:  # about 55 kB each
            self._grounded.clear()
        future = self.runner.post(Ground(episode.id, text, step))
        try:  # the runner answers between two steps: wait that long rather than draw the step twice
            result: Grounding | str = future.result(timeout=GROUNDING_WAIT)
        except FutureTimeout:
            self._grounding.add(key)

            def done(f: Future, key=key) -> None:
                try:
                    late: Grounding | str = f.result()
                except Exception as e:  # noqa: BLE001 - shown to the user
                    late = str(e)
                self._events.put(Grounded(key, late))

            future.add_done_callback(done)
            return None
        except Exception as e:  # noqa: BLE001 - shown to the user
            result = str(e)
        self._grounded[key] = result
        return result

    # -- drawing ------------------------------------------------------------------------------------------------
    def _render(self) -> None:
        v, episode = self.view, self.view.episode
        if episode is None or not episode.steps:
            return
        t0 = time.perf_counter()
        n = len(episode.steps)
        t = max(0, min(v.cursor, n - 1))
        record = episode.steps[t]
        counterfactual = self._counterfactual_at(episode, t)
        grounding = counterfactual if isinstance(counterfactual, Grounding) else None
        layers = None
        if record.maps is not None and self.runner.models.get(episode.checkpoint) is not None:
            heads = self.runner.models[episode.checkpoint].heads
            maps = record.maps.maps
            if grounding:
                maps = {**maps, "relevance_map_w": grounding.relevance_w, "goal_map_w": grounding.goal_w,
                        "goal_map_r": grounding.goal_r}
            layers = map_layers(maps, heads, self.value_mode.value, self.range_mode.value,
                                tuple(lm.noun_phrase for lm in episode.task.world.landmarks))
        positions = self.compare.own_path(episode, np.array([s.position for s in episode.steps[: t + 1]]))
        opacity = float(self.opacity.value)
        with self.client.atomic():
            self.scene.set_drone(record.position, record.yaw, record.T_world_camera, None, record.camera_jpeg)
            self.scene.set_path(positions)
            for name, box in self.layer_boxes.items():
                layer = layers.get(name) if layers is not None and box.value else None
                visible = layer is not None
                self.scene.set_layer(name, layer.rgb if layer else None, layer.alpha if layer else None, opacity,
                                     visible)
        self.camera.content = camera_html(record.camera_jpeg)
        self.readout.content = readout_markdown(episode, t, counterfactual, self.view.counterfactual)
        self.maps.content = maps_html(episode, t, layers, self.view.counterfactual if grounding else None,
                                      self._cell_of) + self.compare.truth_html(episode, t)
        if self.view.counterfactual and grounding is not None:
            self.whatif_note.content = whatif_markdown(grounding, record)
        elif isinstance(counterfactual, str):
            self.whatif_note.content = error_html(html.escape(counterfactual))
        self._inspect(episode, record, grounding)
        self._set_timeline(t, n - 1)
        if (n, t) != v.plot_steps:  # the cursor follows the timeline
            self._update_plot(episode, t)
            v.plot_steps = (n, t)
        self.compare.render(episode, t)
        self.frames_drawn += 1
        if self._clicked_at is not None and episode.started is not None and episode.started > self._clicked_at:
            self.click_to_frame.append(time.perf_counter() - self._clicked_at)  # the server's share of it
            self._clicked_at = None
        if self._whatif_at is not None and grounding is not None:
            self.whatif_to_frame.append(time.perf_counter() - self._whatif_at)
            self._whatif_at = None
        self.render_seconds += time.perf_counter() - t0

    def _inspect(self, episode: Episode, record: StepRecord, grounding: Grounding | None) -> None:
        xy, model = self.view.inspected, self.runner.models.get(episode.checkpoint) if episode.checkpoint else None
        if xy is None:
            return
        world = episode.task.world
        with self.client.atomic():
            self.scene.mark_cell(xy, world.field_size / self.runner.config.model.map_size)
        if record.maps is None or model is None:
            self.inspector.content = "No model maps to inspect in this episode."
            return
        m = record.maps
        report = inspect_cell(xy[0], xy[1], m.semantic_w, grounding.relevance_w if grounding else m.relevance_w,
                              grounding.goal_w if grounding else m.goal_w, model.heads, world)
        self.inspector.content = inspector_markdown(report, record.step)

    def _set_timeline(self, t: int, last: int) -> None:
        self.timeline.max = max(1, last)
        self.timeline.value = t
        episode = self.view.episode
        radius = self.runner.config.task.success_radius
        marks = timeline_marks(episode, radius) if episode is not None else ((0, "0"), (1, "1"))
        marks = self.compare.with_parting(episode, marks)
        if marks != self._marks:
            self._marks = marks
            # viser 1.1 takes marks only at creation; its handle keeps them in the `_marks` prop
            self.timeline._marks = tuple(GuiSliderMark(value=float(v), label=label) for v, label in marks)

    def _update_plot(self, episode: Episode, t: int) -> None:
        self.plot.data = actions_data(episode, t, self.runner.config.task.success_radius)
