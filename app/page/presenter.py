"""Presenter mode: the page made for showing the system to people who do not read code, on a 1280x800 laptop or a
projector. A "Presenter mode" box at the top of the controls (or `?presenter=1` in the page's link) turns it on:

- larger text everywhere (the page's root font size, which every viser control is sized from);
- the 3D view given most of the screen (the controls 470 px wide: 810 of a 1280 px screen are the 3D view's), its
  camera brought as near as the field allows for the canvas's shape, the drone marked with a yellow ring and a
  "drone" label;
- a card at the top of the controls with the instruction and the result in large type, the step, what the drone
  sees, and the three maps labelled in plain words ("where it thinks the goal is"), the drone and the goal marked,
  the semantic map read as this world's landmarks or nothing (`app.render.layers`), and what the colours of the
  maps and of the 3D view's paths mean;
- the developer controls hidden: the page's title and introduction, the environment id, split, policy and mirror
  choices, the word chips, speed, "follow", the counterfactual and ground-layer folders, and the right-hand panel of
  developer panels (its camera and maps are in the card). Run, the instruction, the playback controls and the
  timeline stay, and the Share folder under them: a link copied there opens in presenter mode (`presenter=1`), and
  Export works.

Turning it off shows everything as it was. The mode is the tab's own (like the rest of its view): a projector's tab
can be in presenter mode while a laptop's is not. It also unticks "Show episodes started elsewhere", so that nobody
else's Run moves what the audience sees, and sets the ground's semantic map to this world's landmarks (turning
presenter mode off puts both back as they were).
"""

from __future__ import annotations

import base64
import html
import logging
import threading
import time
import traceback

import viser
from viser._gui_handles import GuiFolderHandle

from app.page.controls import SEMANTIC_READINGS
from app.page.events import OptionsChanged, WatchSet
from app.page.scene import framing_camera
from app.render.colors import DRONE_MARK_RGB, PATHS_LEGEND, png_bytes, swatch_html, upscale
from app.render.export import heads_for as _heads_for
from app.render.export import result_line, step_layers
from app.render.panels import cell_marks_html

log = logging.getLogger("gsmn.dashboard")
# the result table too: the card says the result, and without the table Run and the timeline fit on a 1280x800 screen;
# the landmark chips (one to three rows) too, so that they fit whatever the world; and the World edits box with its
# picker, a developer's tool
HIDDEN = ("checkpoint_note", "env_number", "split", "env_buttons", "policy", "mirror", "follow", "watch_others",
          "speed", "shared_note", "status", "result", "side_chips", "name_chips", "world_edits")
# folders whose labels start so (the glossary too: presenter mode speaks plainly)
HIDDEN_FOLDERS = ("Counterfactual", "Layers on the ground", "Compare and fork", "What the words mean")
SHARE_FOLDER = "Share this step"  # kept, and moved under Playback so that Run and the timeline stay on the screen
STYLE = "<style>html{font-size:19px !important}</style>"
WIDE = 470  # px, the controls' width in presenter mode (330 otherwise): the 3D view keeps 810 px of a 1280 screen
WORLD_READING = next(label for label, reading in SEMANTIC_READINGS.items() if reading == "world")
LABEL = "font-size:0.68rem;font-weight:600;line-height:1.15;margin-bottom:2px"
PRESENTER_TITLES = {"semantic": "What it has mapped", "relevance": "Where it thinks the landmark is",
                    "goal": "Where it thinks the goal is"}


class Presenter:
    def __init__(self, viewer):
        self.viewer = viewer
        self.client: viser.ClientHandle = viewer.client
        self.on = False
        self.watched_before: bool | None = None  # the "started elsewhere" box before presenter mode unticked it
        self.reading_before: str | None = None  # the semantic map's reading before presenter mode chose this world's
        self.share_order: float | None = None  # the Share folder's place before presenter mode moved it
        self.camera_before: tuple | None = None  # the 3D view's camera (position, look_at) before it was framed
        self._framed: float | None = None  # the canvas's aspect the camera was framed for
        self._closing = False
        self._shown: tuple | None = None
        self._lock = threading.RLock()  # the loop's framing and drawing against `set` on another thread
        gui = self.client.gui
        order = viewer.checkpoint_note.order + 0.01  # right under the title, above the Episode folder
        self.toggle = gui.add_checkbox("Presenter mode", False, order=order,
                                       hint="large text, the instruction and result up front, the maps in plain "
                                            "words, developer controls hidden (also ?presenter=1 in the link)")
        self.style = gui.add_html("", order=order + 0.001)
        self.card = gui.add_html("", order=order + 0.002, visible=False)
        self.toggle.on_update(lambda event: self.set(bool(self.toggle.value)) if event.client is not None else None)
        self.thread = threading.Thread(target=self._loop, name="gsmn-presenter", daemon=True)
        self.thread.start()

    def close(self) -> None:
        self._closing = True
        self.thread.join(timeout=5)

    def _folders(self, labels: tuple[str, ...] = HIDDEN_FOLDERS) -> list[GuiFolderHandle]:
        handles = list(self.client.gui._container_handle_from_uuid.values())
        return [h for h in handles if isinstance(h, GuiFolderHandle) and h.label.startswith(labels)]

    def _intro(self) -> list:
        """The page's title and introduction (the card's instruction replaces them), and the truth box that sits
        under the folders (a developer's view)."""
        truth = getattr(getattr(self.viewer, "compare", None), "truth_box", None)
        return [self.viewer.intro, *([truth] if truth is not None else [])]

    def set(self, on: bool) -> None:
        """Presenter mode on or off, in this tab (waits for a frame the loop is drawing)."""
        with self._lock:
            self._set(on)

    def _set(self, on: bool) -> None:
        if on == self.on and self.toggle.value == on:
            return
        self.on = on
        if self.toggle.value != on:
            self.toggle.value = on
        v, gui = self.viewer, self.client.gui
        if on:
            self.watched_before = bool(v.watch_others.value)
            v.watch_others.value = False
        elif self.watched_before is not None:
            v.watch_others.value, self.watched_before = self.watched_before, None
            v._events.put(WatchSet())
        self._set_reading(on)
        with self.client.atomic():
            for name in HIDDEN:
                getattr(v, name).visible = not on
            for handle in (*self._folders(), *self._intro()):
                handle.visible = not on
            v.picker.show(not on)
            self._move_share(on)
            v.panel.visible = not on
            v.scene.mark_drone(on)
            self.style.content = STYLE if on else ""
            self.card.visible = on
            gui.main_panel.set_width(WIDE if on else 330)
        if not on:
            self._unframe()
        self._shown = None

    def _frame(self) -> None:
        """Presenter mode's 3D view: the camera as near as the field allows for the canvas's shape (framed again
        only when the canvas changes shape, so that a person's own turning of the view is left alone)."""
        camera = self.client.camera
        if camera.image_height <= 0:
            return  # the page has not said its canvas's size yet
        aspect = camera.aspect
        if self._framed is not None and abs(aspect - self._framed) < 0.03:
            return
        if self.camera_before is None:
            self.camera_before = (tuple(camera.position), tuple(camera.look_at))
        view = framing_camera(aspect)
        with self.client.atomic():
            camera.position, camera.look_at = view["position"], view["look_at"]
        self._framed = aspect

    def _unframe(self) -> None:
        if self.camera_before is not None:
            with self.client.atomic():
                self.client.camera.position, self.client.camera.look_at = self.camera_before
        self.camera_before = self._framed = None

    def _set_reading(self, on: bool) -> None:
        """The ground's semantic map read as this world's landmarks while presenter mode is on, as before after."""
        box = self.viewer.semantic_reading
        if on:
            self.reading_before, box.value = box.value, WORLD_READING
        elif self.reading_before is not None:
            box.value, self.reading_before = self.reading_before, None
        self.viewer._events.put(OptionsChanged())

    def _move_share(self, on: bool) -> None:
        """The Share folder under the Playback folder in presenter mode (above the fold stay Run and the
        timeline), back in its place after."""
        playback = self._folders(("Playback",))
        for share in self._folders((SHARE_FOLDER,)):
            if on and playback:
                self.share_order = share.order if self.share_order is None else self.share_order
                share.order = playback[0].order + 0.5
            elif not on and self.share_order is not None:
                share.order, self.share_order = self.share_order, None

    def _loop(self) -> None:
        while not self._closing:
            try:
                with self._lock:  # not between a set(False) and its camera put back: that would frame it again
                    if self.on:
                        self._frame()
                        self._draw()
            except Exception:  # noqa: BLE001 - the page lives on
                log.error("presenter card failed:\n%s", traceback.format_exc())
            time.sleep(0.25)

    def _draw(self) -> None:
        v = self.viewer.view
        episode = v.episode
        if episode is None or not episode.steps:
            key = ("world", id(self.viewer.world_shown))
            if key != self._shown:
                self._shown = key
                self.card.content = card_html(None, 0, None)
            return
        t = max(0, min(v.cursor, len(episode.steps) - 1))
        key = (episode.id, t, len(episode.steps), episode.status)
        if key == self._shown:
            return
        self._shown = key
        self.card.content = card_html(episode, t, _heads_for(self.viewer.runner, episode), self.viewer._cell_of)


def _img(data: bytes, mime: str, style: str, attrs: str = "") -> str:
    return f"<img {attrs} src='data:{mime};base64,{base64.b64encode(data).decode('ascii')}' style='{style}'/>"


def scene_key_html() -> str:
    """What the 3D view's marks mean: the drone's ring, the paths and the side to stop on."""
    items = swatch_html(DRONE_MARK_RGB, "yellow ring: the drone") + "".join(swatch_html(rgb, label)
                                                                             for rgb, label in PATHS_LEGEND)
    return (f"<div class='gsmn-paths-legend' style='grid-column:1/-1;font-size:0.68rem;line-height:1.35'>"
            f"<b>In the 3D view:</b> {items}</div>")


def verdict_html(episode) -> str:
    """The result in colour (green success, red failure), or how the episode stands while it has none."""
    r = episode.result
    if r is not None:
        colour = "#1e8449" if r.success else "#c0392b"
        return (f"<div class='gsmn-presenter-result' style='font-size:1rem;font-weight:700;line-height:1.25;"
                f"color:{colour}'>{html.escape(result_line(episode))}</div>")
    return (f"<div class='gsmn-presenter-result' style='font-size:1rem;color:#555'>"
            f"{'Flying…' if episode.live else html.escape(episode.status)}</div>")


def map_cells(episode, t: int, maps: dict, cell_of=None) -> dict[str, str]:
    """Each map of the card titled in plain words, with the drone's cell (white) and the goal's (red) outlined."""
    record, instruction = episode.steps[t], episode.task.instruction
    cells = {}
    for name, rgb in maps.items():
        marks = ""
        if cell_of is not None:
            marks = cell_marks_html([(*cell_of(record.position[0], record.position[1]), (255, 255, 255)),
                                     (*cell_of(instruction.goal_x, instruction.goal_y), (230, 30, 30))], rgb.shape[0])
        image = _img(png_bytes(upscale(rgb, max(1, 200 // rgb.shape[0]))), "image/png",
                     "width:100%;display:block;image-rendering:pixelated", f"data-layer='{name}'")
        cells[name] = (f"<div><div style='{LABEL}'>{html.escape(PRESENTER_TITLES[name])}</div>"
                       f"<div style='position:relative;border-radius:4px;overflow:hidden'>{image}{marks}</div>"
                       + "</div>")
    return cells


def card_html(episode, t: int, heads, cell_of=None) -> str:
    """The presenter's card: the instruction and the result large, the step, the camera and the maps in plain
    words (the semantic map as this world's landmarks or nothing), the drone's cell (white) and the goal's (red)
    outlined on them, and what the colours of the maps and of the 3D view mean."""
    if episode is None:
        return ("<div class='gsmn-presenter' style='font-size:1.3rem;padding:6px 0'>Type an instruction below and "
                "press <b>Run</b>: the drone flies it, and this card shows what it sees and what it thinks.</div>"
                + scene_key_html())
    legends: dict[str, str] = {}
    maps = step_layers(episode, t, heads, legends, "world")
    cells = map_cells(episode, t, maps, cell_of)
    camera = _img(episode.steps[t].camera_jpeg, "image/jpeg", "width:100%;display:block;border-radius:4px")
    key = ("<div style='grid-column:1/-1;font-size:0.68rem;line-height:1.35;color:#333'><b>Maps</b> from above, "
           "north up: yellow likely, dark blue unlikely; white square the drone, red square the goal.</div>")
    # one row, so that the card leaves Run and the timeline on a 1280x800 screen: the camera, then the maps
    grid = (f"<div><div style='{LABEL}'>What the drone sees</div>{camera}</div>"
            + cells.get("goal", "") + cells.get("relevance", "") + cells.get("semantic", "")
            + (f"<div style='grid-column:1/-1'>{legends.get('semantic', '')}</div>" if "semantic" in maps else "")
            + (key if maps else
            "<div style='grid-column:span 3;font-size:0.9rem;opacity:.7'>No model watched this flight: no maps.</div>")
            + scene_key_html())
    return (f"<div class='gsmn-presenter' data-episode='{episode.id}' data-step='{t}' style='padding:2px 12px 2px 0'>"
            f"<div class='gsmn-presenter-instruction' style='font-size:1.4rem;font-weight:700;line-height:1.2'>"
            f"\u201c{html.escape(episode.instruction)}\u201d</div>{verdict_html(episode)}"
            f"<div style='font-size:0.75rem;color:#444;margin:1px 0 4px'>Step {t} of {len(episode.steps) - 1} · "
            f"environment {episode.env_id}</div>"
            "<div style='display:grid;grid-template-columns:minmax(0,1.3fr) repeat(3,minmax(0,1fr));gap:6px;"
            "align-items:start'>"
            f"{grid}</div></div>")
