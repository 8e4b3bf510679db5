"""The page's kept episodes (`app.jobs.kept`): an "Episodes" tab that lists and searches every episode flown in the
page or over the API, replays one in the live view, pins it and exports it; a "Share" folder that makes a link to the
step shown ("Copy link") and downloads the episode as HTML or GIF; and the link read on load.

**The list.** A row says who flew the episode (the checkpoint by the name it is offered by, as a mirror ensemble, or
the expert), what it comes from (a fork's original and step, a comparison's side), and how it ended in its result
line's words and number; successes are green, failures red, the rest grey, and the text wraps rather than being cut
off. "Flown by" offers each checkpoint that flew a kept episode; the note counts as the storage line does.

**Links.** viser gives the server no client's URL, so the page reads its own: an element of the page holds a small
script (an image's onerror handler, which viser's HTML element runs) that writes `location.search` into a hidden
text field, and the field's update reaches the server with its client. `/?episode=123&step=40&layers=goal,relevance`
then opens episode 123 at step 40 with those ground layers (and `presenter=1` turns presenter mode on), in the tab
that opened it only: every tab has its own view (`app.page.viewer`). Opening a kept episode, from the list or a link,
unticks the tab's "Show episodes started elsewhere", so that another tab's Run does not take it away.
A link to an episode no longer kept says so, in the status line and as a notification to the tab that opened it.
"""

from __future__ import annotations

import contextlib
import html
import logging
import threading
import time
import traceback
import uuid
from datetime import datetime
from pathlib import Path
from urllib.parse import parse_qs

import viser

from app.jobs.kept import policies_flown, row_summary, search
from app.live.commands import RunnerListener
from app.page.events import CursorMoved, EpisodeEnded, EpisodeStarted, OptionsChanged
from app.render.panels import error_html

log = logging.getLogger("gsmn.dashboard")
ROWS = 12
LINK_FIELD = "gsmn-link"
OUTCOME_CHOICES = {"any outcome": None, "success": "success", "failure": "failure", "cancelled": "cancelled",
                   "failed": "failed"}
WHEN_CHOICES = {"any time": None, "last hour": 3600.0, "last 24 hours": 86400.0, "last 7 days": 7 * 86400.0}
ANY_POLICY = "any policy"
OUTCOME_COLORS = {"success": "green", "failure": "red"}  # a row's button; cancelled, failed and live ones grey
# the rows' buttons (those after the list's hidden marker, in the Episodes tab) wrap their text instead of cutting
# it off, and read from the left; viser sets each button's height inline
_ROWS = "div:has(> .gsmn-episode-list) ~ div .mantine-Button-"
LIST_STYLE = ("<div class='gsmn-episode-list' style='display:none'></div><style>"
              f"{_ROWS}root{{height:auto !important;min-height:2em;padding-top:5px;padding-bottom:5px}}"
              f"{_ROWS}inner{{justify-content:flex-start}}"
              f"{_ROWS}label{{white-space:normal;text-align:left;line-height:1.35;overflow:visible;height:auto}}"
              "</style>")

# the script that tells the server this tab's URL: it finds the hidden field, hides its row, and types
# location.search into it (with the time, so the same link opened twice is two updates); once per tab's page
# (`read_link_html`), though viser mounts the element again when the controls are reordered (presenter mode)
READ_LINK = ("<img src='data:,' alt='' style='display:none' onerror=\"var d=window.gsmnLinkRead=window.gsmnLinkRead"
             "||{};if(d['__ONCE__'])return;d['__ONCE__']=1;var f=function(n){var l=[].slice.call("
             "document.querySelectorAll('label')).find(function(x){return x.textContent.trim()=='" + LINK_FIELD +
             "'});if(!l){if(n<100)setTimeout(function(){f(n+1)},200);return;}var row=l.closest('.mantine-Flex-root')"
             "||l.parentElement;row.style.display='none';var i=row.querySelector('input');var set=Object."
             "getOwnPropertyDescriptor(HTMLInputElement.prototype,'value').set;set.call(i,location.search+'#'+"
             "Date.now());i.dispatchEvent(new Event('input',{bubbles:true}));i.dispatchEvent(new Event('change',"
             "{bubbles:true}));i.blur();};f(0);\">")


def read_link_html() -> str:
    """The link reader for one tab's page: its script sends the page's URL once, under a token of its own, so that
    viser mounting the element again (a reordered control panel) does not apply the link again (which turned
    presenter mode back on as it was turned off), while the page of a new tab (a reconnection) reads it anew."""
    return READ_LINK.replace("__ONCE__", uuid.uuid4().hex)


def link_query(episode_id: int, step: int, layers: list[str], presenter: bool = False) -> str:
    query = f"?episode={episode_id}&step={step}"
    if layers:
        query += "&layers=" + ",".join(layers)
    return query + ("&presenter=1" if presenter else "")


def link_html(query: str | None) -> str:
    """The link to the view shown, with a Copy link button (the page's origin is the browser's: the script adds it)."""
    if query is None:
        return "<div class='gsmn-share' style='font-size:12px;opacity:.7'>Run or open an episode to link to it.</div>"
    q = html.escape(query, quote=True)
    fill = ("this.parentElement.querySelector('input').value=location.origin+location.pathname+"
            "this.parentElement.dataset.link")
    copy = ("var i=this.parentElement.querySelector('input');var b=this;var done=function(){b.textContent='Copied'};"
            "if(navigator.clipboard&&window.isSecureContext){navigator.clipboard.writeText(i.value).then(done,"
            "function(){i.select();document.execCommand('copy');done()})}else{i.select();document.execCommand('copy');"
            "done()}")
    return (f"<div class='gsmn-share' data-link='{q}' style='display:flex;gap:6px;align-items:center'>"
            f"<input readonly aria-label='link to this step' style='flex:1;font-size:12px;padding:3px;"
            f"border:1px solid #ccc;border-radius:4px' value='{q}'/>"
            f"<button class='gsmn-copy-link' onclick=\"{copy}\" style='padding:3px 10px;border-radius:4px;"
            f"border:1px solid #2870f5;background:#2870f5;color:white;cursor:pointer'>Copy link</button>"
            f"<img src='data:,' alt='' style='display:none' onerror=\"{fill}\"></div>")


# -- a kept episode's row: `row` is its summary (app.jobs.kept.row_summary); `names` a checkpoint folder's name -------
def checkpoint_names(runner) -> dict[str, str]:
    """The name each checkpoint folder is offered by (gsmn, table2/no-ground, run-3), by its resolved path."""
    names = {}
    for info in runner.checkpoint_list():
        with contextlib.suppress(OSError):
            names.setdefault(Path(info.path).resolve().as_posix(), info.name)
    return names


def flier(policy: str, checkpoint: str | None, names: dict[str, str]) -> str:
    """Who flew, as the comparison's captions say it: the expert, or the model by its checkpoint's name (a folder
    offered by no name: its last part), and whether as a mirror ensemble."""
    if policy == "expert":
        return "expert"
    name = names.get(checkpoint, checkpoint) if checkpoint else "?"
    if Path(name).is_absolute():
        name = Path(name).name
    return f"model {name}" + (", mirror ensemble" if policy == "mirror" else "")


def outcome(row: dict) -> str:
    """success or failure once finished, else its status (cancelled, failed, running...)."""
    result = row["result"]
    return ("success" if result["success"] else "failure") if row["status"] == "finished" and result else row["status"]


def ending(row: dict) -> str:
    """How it ended, in the words and number of its result line: 'said STOP after 99 steps' counts the actions flown
    (the steps recorded count its start too, one more); unfinished, the timeline's last step."""
    r = row["result"]
    if row["status"] == "finished" and r is not None:
        return f"{'said STOP' if r['stopped'] else 'ran out of steps'} after {r['steps']} steps"
    n = row["steps"]
    return f"at step {n - 1}" if n else "before its first step"


def relation(row: dict) -> list[str]:
    """Where it comes from: a fork's original and step, a comparison's side and other episode; and what was changed:
    its world, or a map (a map intervention)."""
    out = []
    if row.get("fork_of") is not None:
        out.append(f"fork of #{row['fork_of']} at step {row['fork_step']}")
    if row.get("comparison") is not None:
        other = f" with #{row['compared_with']}" if row.get("compared_with") is not None else ""
        out.append(f"side {row['comparison_side']} of a comparison{other}")
    if row.get("world_edits"):
        out.append("edited world")
    if row.get("intervention"):
        from gsmn.analysis.intervention import LABELS

        iv = row["intervention"]
        out.append(LABELS.get(iv.get("map"), "a changed map") if iv.get("with", "truth") == "truth"
                   else f"painted {iv.get('map')} map")
    return out


def row_label(row: dict, names: dict[str, str]) -> str:
    when = datetime.fromtimestamp(row["created"]).strftime("%d %b %H:%M")
    parts = [f"#{row['id']}", outcome(row) + (" · pinned" if row["pinned"] else ""), row["instruction"],
             f"env {row['env_id']}", flier(row["policy"], row["checkpoint"], names), *relation(row), ending(row),
             when]
    return " · ".join(parts)


def row_hint(row: dict, names: dict[str, str]) -> str:
    """The button's hint: what the label leaves out."""
    r = row["result"]
    watched = f", {flier('model', row['checkpoint'], names)} watching" if (
        row["policy"] == "expert" and row["checkpoint"]) else ""
    parts = [f"Episode {row['id']}, flown {datetime.fromtimestamp(row['created']).strftime('%d %b %Y %H:%M:%S')}"
             f"{watched}", f"{r['goal_distance']:.1f} m from the goal" if r else None,
             f"typed as \"{row['typed_instruction']}\"" if row.get("typed_instruction") else None,
             f"checkpoint folder {row['checkpoint']}" if row["checkpoint"] else None,
             row["error"].rstrip(".") if row["error"] else None, "click to replay it at its last step"]
    return ". ".join(p for p in parts if p) + "."


def row_color(row: dict) -> str:
    return OUTCOME_COLORS.get(outcome(row), "gray")


def list_note(shown: int, matching: int, total: int, filtered: bool) -> str:
    """What the list shows, counted as the storage line under it counts the kept episodes."""
    if not shown:
        return "No kept episode matches the search." if total else "No episode kept yet: run one."
    note = f"{shown} of {total} kept episode{'s' if total != 1 else ''} shown"
    if filtered:
        note += f": {matching} match{'es' if matching == 1 else ''} the search"
    if matching > shown:
        note += ", the newest first (narrow the search for older ones)"
    return note + ". Click one to replay it."


class EpisodesView(RunnerListener):
    """The Episodes tab and the Share folder of one tab, beside its `viewer` (app.page.viewer.Viewer)."""

    def __init__(self, viewer, keeper, presenter=None):
        self.viewer, self.keeper = viewer, keeper
        self.store, self.db = keeper.store, keeper.db
        self.client: viser.ClientHandle = viewer.client
        self.presenter = presenter  # app.page.presenter.Presenter, turned on by a link's presenter=1
        self.rows: list[dict] = []
        self.policies: dict[str, tuple[str | None, str | None]] = {ANY_POLICY: (None, None)}  # choice -> its filter
        self.selected: int | None = None
        self._closing = False
        self._shown: tuple | None = None
        self._last_link: tuple | None = None
        self._build()
        viewer.runner.listeners.append(self)
        self.refresh()
        self.thread = threading.Thread(target=self._loop, name="gsmn-episodes-view", daemon=True)
        self.thread.start()

    def close(self) -> None:
        self._closing = True
        with contextlib.suppress(ValueError):
            self.viewer.runner.listeners.remove(self)
        self.thread.join(timeout=5)

    # -- the GUI ----------------------------------------------------------------------------------------------
    def _build(self) -> None:
        gui = self.client.gui
        self.link_field = gui.add_text(LINK_FIELD, "")
        self.link_reader = gui.add_html(read_link_html())
        self.link_field.on_update(self._on_link)
        after = getattr(self.viewer, "result", None)  # right under the result, above the counterfactual
        with gui.add_folder("Share this step", order=after.order + 0.01 if after is not None else None):
            self.share = gui.add_html(link_html(None))
            self.pin_box = gui.add_checkbox("Pinned", False, hint="a pinned episode is never removed by the retention "
                                            "limit")
            self.export_buttons = gui.add_button_group("Export", ("HTML", "GIF", "MP4"))
            self.share_note = gui.add_markdown("The HTML page plays the episode back in any browser, with no server; "
                                               "the GIF and the MP4 show the camera beside the maps, for slides.")
        self.pin_box.on_update(self._on_pin)
        self.export_buttons.on_click(self._on_export)
        with self.viewer.panel.add_tab("Episodes", viser.Icon.LIST):
            self.search_text = gui.add_text("Instruction has", "", hint="a part of the instruction, any case")
            self.search_env = gui.add_text("Environment", "", hint="an environment id, or empty for any")
            self.search_outcome = gui.add_dropdown("Outcome", tuple(OUTCOME_CHOICES))
            self.search_policy = gui.add_dropdown("Flown by", (ANY_POLICY,), hint="the policy: each checkpoint "
                                                  "flown (as itself or a mirror ensemble), or the expert")
            self.search_when = gui.add_dropdown("Flown", tuple(WHEN_CHOICES))
            self.search_pinned = gui.add_checkbox("Pinned only", False)
            self.search_button = gui.add_button("Search", icon=viser.Icon.SEARCH)
            self.list_note = gui.add_markdown("")
            self.list_style = gui.add_html(LIST_STYLE)
            self.row_buttons = [gui.add_button(f"row {k}", visible=False) for k in range(ROWS)]
            self.storage = gui.add_markdown("")
        self.search_button.on_click(lambda _: self.refresh())
        for control in (self.search_outcome, self.search_policy, self.search_when, self.search_pinned):
            control.on_update(lambda e: self.refresh() if e.client is not None else None)  # not refresh's own
        for k, button in enumerate(self.row_buttons):
            button.on_click(lambda event, k=k: self._open_row(k, event.client))

    # -- the list ---------------------------------------------------------------------------------------------
    def refresh(self) -> None:
        """Search the record with the tab's filters and show the newest matches."""
        try:
            env_text = self.search_env.value.strip()
            if env_text and not env_text.isdigit():
                self.list_note.content = error_html("The environment is a number (e.g. 70), or empty for any.")
                return
            self.keeper.flush(2.0)
            names = checkpoint_names(self.viewer.runner)
            self._offer_policies(names)
            policy, checkpoint = self.policies.get(self.search_policy.value, (None, None))
            within = WHEN_CHOICES[self.search_when.value]
            filters = dict(env_id=int(env_text) if env_text else None,
                           instruction=self.search_text.value.strip() or None, policy=policy, checkpoint=checkpoint,
                           outcome=OUTCOME_CHOICES[self.search_outcome.value],
                           pinned=True if self.search_pinned.value else None,
                           since=time.time() - within if within else None)
            rows = search(self.db, **filters, limit=ROWS)
            matching = len(search(self.db, **filters, limit=10**9, columns="id"))
            counts = self.db.kept_counts()
        except Exception as e:  # noqa: BLE001 - a record that cannot be read is said, not raised into viser
            self.list_note.content = error_html(f"Cannot read the record: {html.escape(str(e))}")
            return
        self.rows = [row_summary(r) for r in rows]
        filtered = any(v is not None for v in filters.values())
        self.list_note.content = list_note(len(self.rows), matching, counts["episodes"], filtered)
        self._show_rows(names)
        self.storage.content = (f"*{counts['episodes']} kept, {counts['pinned']} pinned: "
                                f"{self.db.kept_bytes() / 1e6:.1f} MB of {self.keeper.limit_bytes / 1e6:.0f} MB; past "
                                "it the oldest unpinned are removed.*")

    def _offer_policies(self, names: dict[str, str]) -> None:
        """The Policy filter's choices: any, each checkpoint flown (itself, or as a mirror ensemble), the expert."""
        choices: dict[str, tuple[str | None, str | None]] = {ANY_POLICY: (None, None)}
        for policy, checkpoint in policies_flown(self.db):
            label = flier(policy, checkpoint, names)
            if label in choices:  # two folders of one name
                label += f" ({checkpoint})"
            choices[label] = (policy, checkpoint)
        self.policies = choices
        if tuple(choices) != tuple(self.search_policy.options):
            self.search_policy.options = tuple(choices)  # a choice no longer flown (removed) goes back to any

    def _show_rows(self, names: dict[str, str]) -> None:
        """Each row's button: who flew it, how it ended, green for a success and red for a failure."""
        for k, button in enumerate(self.row_buttons):
            if k < len(self.rows):
                row = self.rows[k]
                button.label, button.hint, button.color = row_label(row, names), row_hint(row, names), row_color(row)
                button.visible = True
            else:
                button.visible = False

    def on_episode_end(self, episode) -> None:  # the runner's thread: the list gains it once written
        threading.Thread(target=self._refresh_later, daemon=True).start()

    def _refresh_later(self) -> None:
        time.sleep(0.5)
        if not self._closing:
            try:
                self.refresh()
            except Exception:  # noqa: BLE001
                log.error("episode list refresh failed:\n%s", traceback.format_exc())

    def _open_row(self, k: int, client) -> None:
        if k < len(self.rows):
            self.open(self.rows[k]["id"], None, None, client)

    # -- opening an episode -------------------------------------------------------------------------------------
    def open(self, episode_id: int, step: int | None, layers: list[str] | None, client=None) -> bool:
        """Show a kept episode in the page at `step` (None: its last) with `layers` on the ground (None: as
        they are). False, with the reason shown, when it is not kept."""
        viewer = self.viewer
        episode = self.store.get(episode_id)
        if episode is None:
            why = self.store.missing(episode_id)
            viewer.status.content = error_html(f"**Link:** {html.escape(why)}.")
            if client is not None:
                client.add_notification("Episode not found", why, color="red", auto_close_seconds=15.0)
            return False
        if not episode.steps:
            viewer.status.content = error_html(f"**Link:** episode {episode_id} has no steps yet.")
            return False
        if layers is not None:
            for name, box in viewer.layer_boxes.items():
                box.value = name in layers
            viewer._events.put(OptionsChanged())
        if viewer.watch_others.value:  # a replay of one's own: another tab's Run does not take it away
            viewer.watch_others.value = False
        if self.presenter is not None and self.presenter.on:  # and leaving presenter mode does not tick it again
            self.presenter.watched_before = False
        if episode is not viewer.view.episode:
            viewer._events.put(EpisodeStarted(episode, opened=True))
            if not episode.live:
                viewer._events.put(EpisodeEnded(episode))
        last = len(episode.steps) - 1
        viewer._events.put(CursorMoved(last if step is None else max(0, min(step, last))))
        self.selected = episode_id
        return True

    def _on_link(self, event: viser.GuiEvent) -> None:
        if event.client is None:
            return
        value = self.link_field.value
        key = (event.client.client_id, value)
        if key == self._last_link:  # the script's input and change events: one link
            return
        self._last_link = key
        query = value.split("#", 1)[0].lstrip("?")
        if query:
            self.apply_link(query, event.client)

    def apply_link(self, query: str, client=None) -> None:
        params = {k: v[-1] for k, v in parse_qs(query).items()}
        if self.presenter is not None and params.get("presenter") in ("1", "true", "on"):
            self.presenter.set(True)
        if "episode" not in params:
            return
        try:
            episode_id = int(params["episode"])
            step = int(params["step"]) if "step" in params else None
            if episode_id < 1 or (step is not None and step < 0):
                raise ValueError
        except ValueError:
            self.viewer.status.content = error_html("**Link:** episode and step must be whole numbers "
                                                    f"(episode from 1, step from 0): {html.escape(query)}")
            return
        layers = None
        if "layers" in params:
            asked = [name for name in params["layers"].split(",") if name]
            unknown = [n for n in asked if n not in self.viewer.layer_boxes]
            layers = [n for n in asked if n in self.viewer.layer_boxes]
            if unknown:
                self.viewer.result.content = (f"*Link: no ground layer {html.escape(', '.join(unknown))}; the layers "
                                              f"are {', '.join(self.viewer.layer_boxes)}.*")
        self.open(episode_id, step, layers, client)

    # -- share: the link, the pin and the exports -------------------------------------------------------------
    def current(self) -> tuple | None:
        v = self.viewer.view
        if v.episode is None or not v.episode.steps:
            return None
        layers = [name for name, box in self.viewer.layer_boxes.items() if box.value]
        presenter = bool(self.presenter is not None and self.presenter.on)
        return v.episode.id, max(0, min(v.cursor, len(v.episode.steps) - 1)), tuple(layers), presenter

    def _loop(self) -> None:
        """Keep the link, and the pin box, in step with what the page shows (twice a second)."""
        while not self._closing:
            try:
                shown = self.current()
                if shown != self._shown:
                    self._shown = shown
                    self.share.content = link_html(link_query(shown[0], shown[1], list(shown[2]), shown[3])
                                                   if shown else None)
                    if shown is not None:
                        self.selected = shown[0]
                        pinned = self.store.pinned(shown[0])
                        if self.pin_box.value != pinned:
                            self.pin_box.value = pinned
            except Exception:  # noqa: BLE001 - the page lives on
                log.error("share panel update failed:\n%s", traceback.format_exc())
            time.sleep(0.5)

    def _on_pin(self, event: viser.GuiEvent) -> None:
        if event.client is None:
            return
        shown = self.current()
        if shown is None:
            self.share_note.content = "Run or open an episode to pin it."
            return
        self.keeper.flush(2.0)
        if self.db.kept(shown[0]) is None:
            self.share_note.content = f"Episode {shown[0]} is not in the record yet."
            return
        self.db.update_kept(shown[0], pinned=int(bool(self.pin_box.value)))
        self.share_note.content = (f"Episode {shown[0]} pinned: the retention limit never removes it."
                                   if self.pin_box.value else f"Episode {shown[0]} unpinned.")
        self.refresh()

    def _on_export(self, event: viser.GuiEvent) -> None:
        from app.render.export import export_episode, heads_for

        shown = self.current()
        if shown is None or event.client is None:
            self.share_note.content = "Run or open an episode to export it."
            return
        fmt = event.target.value.lower()
        episode = self.store.get(shown[0])
        if episode is None:
            self.share_note.content = error_html(html.escape(self.store.missing(shown[0])))
            return
        self.share_note.content = f"Exporting episode {episode.id} as {fmt.upper()}..."
        try:
            data = export_episode(episode, fmt, heads_for(self.viewer.runner, episode))
        except ValueError as e:
            self.share_note.content = error_html(html.escape(str(e)))
            return
        name = f"episode-{episode.id}.{fmt}"
        event.client.send_file_download(name, data, save_immediately=True)
        self.share_note.content = f"Exported {name} ({len(data) / 1e6:.1f} MB, {len(episode.steps)} steps)."

