"""One tab's controls (viser GUI; built on the tab's connection, called back on viser's thread pool): the Episode,
Playback, Counterfactual and Layers folders on the left and the Camera and maps and Actions tabs on the right, and
what a person's clicks and typing do. Callbacks only post runner commands and put events on the tab's queue
(`app.page.events`); the tab's UI thread (`app.page.viewer`) applies them.
"""


from __future__ import annotations

import html
import threading
import time
from concurrent.futures import Future

import numpy as np
import viser
import viser.uplot

from app.live.commands import (
    SetSpeed,
    ShowEnv,
    StartEpisode,
)
from app.live.models import FIRST_PERSON_KINDS, LIVE_KINDS
from app.live.recording import jpeg_bytes
from app.page.compare_view import CompareView
from app.page.events import (
    CursorMoved,
    FollowSet,
    GroundClicked,
    OptionsChanged,
    PlaybackPressed,
    ShowAnswered,
    SidesTyped,
    StartAnswered,
    TaskVisibility,
    WatchLive,
    WatchSet,
    WhatIf,
)
from app.page.world_edit_view import WorldEditPicker
from app.render.colors import paths_legend_html
from app.render.glossary import glossary_markdown
from app.render.layers import LAYERS, RANGE_MODES, VALUE_MODES, frame_of, map_title
from app.render.panels import (
    ACTIONS_AXES,
    ACTIONS_SCALES,
    ACTIONS_SERIES,
    CELL_FIELD,
    HIDE_CELL_FIELD,
    camera_html,
    compose_instruction,
    error_html,
    parse_cell_click,
    parse_env_id,
    placeholder_html,
    side_help,
    suggestions,
    which_landmark,
)
from gsmn.model.grid import cell_centre
from gsmn.task.edits import EditError, edits_from_text
from gsmn.task.instructions import SIDES
from gsmn.task.understand import understand
from gsmn.world.spec import SPLITS, split_env_ids, split_of, world_for_env

EXPERT_CHOICE = "Expert (oracle)"
SPEEDS = {"as fast as it goes": None, "real time (5 steps/s)": 5.0, "2x (10 steps/s)": 10.0,
          "slow (2 steps/s)": 2.0}
FOLLOW_LABEL = "Follow the live step"
WATCH_LABEL = "Show episodes started elsewhere"
ENV_TYPED_WAIT = 0.6  # s without a keystroke before a typed environment id shows its world
INSPECT_HINT = "Click a world map, or the field in the 3D view, to read a map cell."
# the Semantic map box's readings (app.render.layers.SEMANTIC_READINGS): presenter mode chooses the second
SEMANTIC_READINGS = {"all 63 landmark classes": "all", "this world's landmarks": "world"}
SHARED_NOTE = ("<small>This tab has its own timeline, episode, counterfactual and layers. **Shared by every tab:** "
               "the one simulator (one episode flies at a time: Run, Pause, Step, Stop and Speed act on it for "
               "everyone) and the jobs.</small>")


def parse_env_id_or_none(text: str) -> int | None:
    try:
        return parse_env_id(text)
    except ValueError:
        return None


def speed_choice(steps_per_second: float | None) -> str:
    """The Speed box's entry for a pace: one of SPEEDS, or the figure itself."""
    for label, value in SPEEDS.items():
        if value == steps_per_second:
            return label
    return f"{steps_per_second:g} steps/s"  # set in code (SetSpeed), not one of the choices


class ViewerControls:
    """The controls part of `app.page.viewer.Viewer` (its GUI handles are attributes of the viewer)."""

    # -- the GUI ----------------------------------------------------------------------------------------------
    def _build_controls(self, env_id: int) -> None:
        gui = self.client.gui
        gui.configure_theme(dark_mode=False, show_logo=False, brand_color=(40, 110, 245))
        gui.main_panel.dock_left()
        gui.main_panel.set_width(330)
        self.intro = gui.add_markdown("**GSMN dashboard**: follow an instruction with the Grounded Semantic Mapping "
                                      "Network (Blukis et al., RSS 2018) and watch what it maps, grounds and plans.")
        self.checkpoint_note = gui.add_markdown(self._checkpoint_text())
        self._build_episode_folder(gui, env_id)
        self._build_playback_folder(gui)
        with gui.add_folder("Counterfactual: another instruction, same map"):
            self.whatif = gui.add_text("What if", "", hint="grounded on the semantic map at the shown step")
            self.whatif_buttons = gui.add_button_group("Ground", ("Ground", "Clear"))
            self.whatif_note = gui.add_markdown("Type another instruction: its relevance and goal maps and the action "
                                                "it would give appear at once, on the map already built.")
        self.compare = CompareView(self)  # comparisons, forks and the ground truth (app.page.compare_view)
        self.compare.build_controls(gui)
        self._build_layers_folder(gui)
        with gui.add_folder("What the words mean", expand_by_default=False):  # tooltips on the words say the same
            self.glossary = gui.add_markdown(glossary_markdown())
        self._connect_controls()

    def _build_episode_folder(self, gui, env_id: int) -> None:
        with gui.add_folder("Episode"):
            # a text box, not a number box: the browser's number box turns "-5" or "abc" silently into 0
            self.env_number = gui.add_text("Environment id", str(env_id),
                                           hint="a whole number; id % 100: 0-69 train, 70-84 test, 85-99 dev")
            self.split = gui.add_dropdown("Split", SPLITS, initial_value=split_of(env_id))
            self.env_buttons = gui.add_button_group("World", ("Show", "Random in split"))
            choices = self._policy_choices()
            self._default_choice = choices[0]
            self.policy = gui.add_dropdown("Policy", choices, initial_value=choices[0],
                                           hint=" ".join(("the expert flies with the model watching, when there is "
                                                          "one.", self.not_live_note())).strip())
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
            self.world_edits = gui.add_text("World edits", "", hint="fly an edited world: 'move pumpkin to 12 20.5; "
                                            "remove box; add tank at 4 9' (x, y in m, 0-30; docs/compare.md)")
            self.picker = WorldEditPicker(self, gui)  # or picked in the 3D view (app.page.world_edit_view)
            self.run_button = gui.add_button("Run", color="green", icon=viser.Icon.PLAYER_PLAY,
                                              hint="fly this instruction in this world from the start")
            self.status = gui.add_markdown("")
            self.elsewhere = gui.add_markdown("", visible=False)  # an episode flying that this tab does not show
            self.watch_live = gui.add_button("Watch it", icon=viser.Icon.EYE, visible=False,
                                             hint="show the episode flying now in this tab")
            # the result right under the status: on a 1280 x 800 screen it shows without scrolling
            self.result = gui.add_markdown("")

    def _build_playback_folder(self, gui) -> None:
        with gui.add_folder("Playback"):
            self.playback = gui.add_button_group("Control", ("Play", "Pause", "Step", "Stop"))
            self.timeline = gui.add_slider("Step", min=0, max=1, step=1, initial_value=0)
            self.follow = gui.add_checkbox(FOLLOW_LABEL, True)
            self.watch_others = gui.add_checkbox(WATCH_LABEL, False,
                                                 hint="ticked, episodes flown from other tabs or the API appear here "
                                                      "as they start; unticked (a new tab), this tab stays on its own")
            speed = speed_choice(self.runner.speed)
            self.speed = gui.add_dropdown("Speed", self._speed_options(speed), initial_value=speed,
                                          hint="the simulator's pace, for every tab")
            self.shared_note = gui.add_markdown(SHARED_NOTE)

    def _build_layers_folder(self, gui) -> None:
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
            self.semantic_reading = gui.add_dropdown(
                "Semantic map reads", tuple(SEMANTIC_READINGS), initial_value="all 63 landmark classes",
                hint="all 63 classes the head knows (open ground reads as any of them), or only this world's "
                     "landmarks and 'nothing': the likeliest of those per cell")
            self.show_task = gui.add_checkbox("Goal, success region, paths", True)
            self.paths_legend = gui.add_html(paths_legend_html())

    def _connect_controls(self) -> None:
        """What each control does when a person uses it (viser's thread pool)."""
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
        for control in (self.opacity, self.value_mode, self.range_mode, self.semantic_reading):
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
            self.inspector = gui.add_markdown(INSPECT_HINT)
            self.cell_field = gui.add_text(CELL_FIELD, "")  # hidden: a world map's click script types its cell here
            self.cell_field.on_update(self._on_map_click)
            gui.add_html(HIDE_CELL_FIELD)
            self.announce_cell = False
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

    def _policy_choices(self, first_person: bool = False) -> tuple[str, ...]:
        """The policy menu: every GSMN checkpoint offered (the default first), then the expert. `first_person` adds
        the first-person baselines (GS-FPV, GS-FPV-MEM), which the Failures and Fine-tune tabs evaluate and train but
        the live view cannot fly: they build no map to show (`not_live_note`)."""
        kinds = LIVE_KINDS + (FIRST_PERSON_KINDS if first_person else ())
        choices = []
        for info in self.runner.checkpoint_list():
            if info.kind in kinds and (info.loaded or info.error is None):
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

    def not_live_note(self) -> str:
        """Which checkpoints offered the live view leaves out, and why ("" when none)."""
        names = [info.label or info.name for info in self.runner.checkpoint_list() if info.kind in FIRST_PERSON_KINDS]
        if not names:
            return ""
        return (f"Not flown here: {', '.join(names)}. First-person baselines build no map, so the live view has none "
                "of their reasoning to show; evaluate them in the Failures tab.")

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
        self._show_typed_world(env_id)

    def _show_typed_world(self, env_id: int) -> None:
        """Show the world of an id typed, once the typing has paused (ENV_TYPED_WAIT), so that the 3D view, the
        instruction and the chips all speak of the world whose id the box holds."""
        shown = self.world_shown.world.env_id if self.world_shown is not None else None
        if self._env_timer is not None:
            self._env_timer.cancel()
        if env_id == shown:
            return
        typed = time.perf_counter()

        def show() -> None:  # not once Run was pressed since, nor when the box holds another id by then
            if self._closing or self._last_run > typed:
                return
            if parse_env_id_or_none(self.env_number.value) == env_id:
                self._post(ShowEnv(env_id), ShowAnswered)

        self._env_timer = threading.Timer(ENV_TYPED_WAIT, show)
        self._env_timer.daemon = True
        self._env_timer.start()

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
        self._clicked_at = self._last_run = time.perf_counter()
        policy, checkpoint = self._policy_of_choice()
        text = self.instruction.value.strip() or None
        env_id = self._env_id()
        if env_id is None:
            return
        try:  # named in the environment's own world
            edits = edits_from_text(self.world_edits.value, world_for_env(env_id, self.runner.config.world))
        except EditError as e:
            self.status.content = f"**Not started:** {e}"
            return
        self.status.content = "Starting..."
        self._post(StartEpisode(env_id, text, policy, checkpoint, preempt=True, paused=paused, world_edits=edits),
                   StartAnswered)

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
            self._can_fly(True, None, typed=False)
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

    def _can_fly(self, ok: bool, sides, typed: bool = True) -> None:
        self.run_button.color = "green" if ok else "gray"
        self._events.put(SidesTyped(sides, typed))

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
        if self.picker.ground_clicked(x, y):  # a picked landmark moved there
            return
        self.announce_cell = True  # the readout lies under the maps: a click also gets a notification
        self._events.put(GroundClicked(x, y))

    def _on_map_click(self, event: viser.GuiEvent) -> None:
        """A world map clicked (its script types the cell into the hidden field): read that cell."""
        n = self.runner.config.model.map_size
        cell = parse_cell_click(self.cell_field.value, n) if event.client is not None else None
        if cell is not None:
            self._on_ground_click(*cell_centre(*cell, self.runner.config.world.field_size, n))

    def _on_landmark_click(self, name: str, index: int | None = None) -> None:
        """A landmark clicked in the 3D view goes into the instruction (the rest of it kept), or is picked to edit."""
        if self.picker.picking and index is not None:
            self.picker.landmark_clicked(index)
        else:
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
