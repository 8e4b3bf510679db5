"""Presenter mode: the page made for showing the system to people who do not read code, on a 1280x800 laptop or a
projector. A "Presenter mode" box at the top of the controls (or `?presenter=1` in the page's link) turns it on:

- larger text everywhere (the page's root font size, which every viser control is sized from);
- a card at the top of the controls with the instruction and the result in large type, the step, what the drone
  sees, and the three maps labelled in plain words ("where it thinks the goal is"), the drone and the goal marked;
- the developer controls hidden: the page's title and introduction, the environment id, split, policy and mirror
  choices, speed, "follow", the counterfactual and ground-layer folders, and the right-hand panel of developer
  panels (its camera and maps are in the card). Run, the instruction, the playback controls and the timeline stay.

Turning it off shows everything as it was. The mode is the tab's own (like the rest of its view): a projector's tab
can be in presenter mode while a laptop's is not. It also unticks "Show episodes started elsewhere", so that nobody
else's Run moves what the audience sees (turning presenter mode off puts the box back as it was).
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

from app.page.events import WatchSet
from app.render.colors import png_bytes, upscale
from app.render.export import heads_for as _heads_for
from app.render.export import result_line, step_layers
from app.render.panels import cell_marks_html

log = logging.getLogger("gsmn.dashboard")
# the result table too: the card says the result, and without the table Run and the timeline fit on a 1280x800 screen
HIDDEN = ("checkpoint_note", "env_number", "split", "env_buttons", "policy", "mirror", "follow", "watch_others",
          "speed", "shared_note", "status", "result", "side_chips")
HIDDEN_FOLDERS = ("Counterfactual", "Layers on the ground", "Compare and fork", "Share this step")  # labels starting so
STYLE = "<style>html{font-size:19px !important}</style>"
WIDE = 720  # px, the controls' width in presenter mode (330 otherwise): the 3D view keeps 560 px of a 1280 screen
LABEL = "font-size:0.8rem;font-weight:600;line-height:1.2;margin-bottom:2px"
PRESENTER_TITLES = {"semantic": "What it has mapped", "relevance": "Where it thinks the landmark is",
                    "goal": "Where it thinks the goal is"}


class Presenter:
    def __init__(self, viewer):
        self.viewer = viewer
        self.client: viser.ClientHandle = viewer.client
        self.on = False
        self.watched_before: bool | None = None  # the "started elsewhere" box before presenter mode unticked it
        self._closing = False
        self._shown: tuple | None = None
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

    def _folders(self) -> list[GuiFolderHandle]:
        handles = list(self.client.gui._container_handle_from_uuid.values())
        return [h for h in handles if isinstance(h, GuiFolderHandle) and h.label.startswith(HIDDEN_FOLDERS)]

    def _intro(self) -> list:
        """The page's title and introduction (the card's instruction replaces them)."""
        return [self.viewer.intro]

    def set(self, on: bool) -> None:
        """Presenter mode on or off, in this tab."""
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
        with self.client.atomic():
            for name in HIDDEN:
                getattr(v, name).visible = not on
            for handle in (*self._folders(), *self._intro()):
                handle.visible = not on
            v.panel.visible = not on
            self.style.content = STYLE if on else ""
            self.card.visible = on
            gui.main_panel.set_width(WIDE if on else 330)
        self._shown = None

    def _loop(self) -> None:
        while not self._closing:
            try:
                if self.on:
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


def card_html(episode, t: int, heads, cell_of=None) -> str:
    """The presenter's card: the instruction and the result large, the step, the camera and the maps in plain
    words, the drone's cell (white) and the goal's (red) outlined on them."""
    if episode is None:
        return ("<div class='gsmn-presenter' style='font-size:1.3rem;padding:6px 0'>Type an instruction below and "
                "press <b>Run</b>: the drone flies it, and this card shows what it sees and what it thinks.</div>")
    r = episode.result
    if r is not None:
        colour = "#1e8449" if r.success else "#c0392b"
        verdict = (f"<div class='gsmn-presenter-result' style='font-size:1.15rem;font-weight:700;color:{colour}'>"
                   f"{html.escape(result_line(episode))}</div>")
    else:
        verdict = (f"<div class='gsmn-presenter-result' style='font-size:1.15rem;color:#555'>"
                   f"{'Flying…' if episode.live else html.escape(episode.status)}</div>")
    record, instruction = episode.steps[t], episode.task.instruction
    legends: dict[str, str] = {}
    maps = step_layers(episode, t, heads, legends)
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
    camera = _img(record.camera_jpeg, "image/jpeg", "width:100%;display:block;border-radius:4px")
    key = ("<div style='grid-column:1/-1;font-size:0.75rem;line-height:1.35;color:#333'>Yellow: likely; dark blue: "
           "unlikely. White square: the drone; red square: the goal. Maps seen from above, north up.</div>")
    # one row, so that the card leaves Run and the timeline on a 1280x800 screen: the camera, then the maps
    grid = (f"<div><div style='{LABEL}'>What the drone sees</div>{camera}</div>"
            + cells.get("goal", "") + cells.get("relevance", "") + cells.get("semantic", "")
            + (f"<div style='grid-column:1/-1'>{legends.get('semantic', '')}</div>" if "semantic" in maps else "")
            + (key if maps else
            "<div style='grid-column:span 3;font-size:0.9rem;opacity:.7'>No model watched this flight: no maps.</div>"))
    return (f"<div class='gsmn-presenter' data-episode='{episode.id}' data-step='{t}' style='padding:2px 12px 2px 0'>"
            f"<div class='gsmn-presenter-instruction' style='font-size:1.5rem;font-weight:700;line-height:1.2'>"
            f"\u201c{html.escape(episode.instruction)}\u201d</div>{verdict}"
            f"<div style='font-size:0.85rem;color:#444;margin:2px 0 6px'>Step {t} of {len(episode.steps) - 1} · "
            f"environment {episode.env_id}</div>"
            "<div style='display:grid;grid-template-columns:minmax(0,1.5fr) repeat(3,minmax(0,1fr));gap:8px;"
            "align-items:start'>"
            f"{grid}</div></div>")
