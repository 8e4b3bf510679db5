"""What the page says and draws beside the 3D scene, as pure functions of an episode and a step: the status and
result text, the world's landmarks counted, the step readout, the counterfactual note, the timeline marks, the
Actions plot's columns, the instruction help (the environment id checked, this world's names suggested, the
template filled in, which landmark an ambiguous name means), the cell inspector, the camera panel and the map
panels (HTML).

Images go to the page as they are: the camera image as the JPEG the runner recorded, each map as a PNG with one
pixel per cell, both scaled up by the browser with `image-rendering: pixelated`, so every pixel and cell stays a
sharp square; the marked cells are outlines drawn over the map by CSS. Nothing is upscaled or re-encoded here
(measured: that took about half of the page's drawing time per step).
"""

from __future__ import annotations

import base64
import html
import math

import numpy as np

from app.live.commands import MAX_ENV_ID, Grounding
from app.live.recording import FINISHED, Episode, StepRecord
from app.render.colors import data_uri, png_bytes
from app.render.glossary import glossed
from app.render.layers import CellReport, Layer
from gsmn.task.metrics import steps_in_success_region

PIXELATED = "width:100%;image-rendering:pixelated;display:block"
WHATIF_LAYERS = ("relevance", "goal", "goal_robot")  # the layers a what-if instruction grounds anew
ORIENTATIONS = {"world": "north up", "robot": "ahead up", "camera": "the camera's view"}


def error_html(text: str) -> str:
    return f"<span style='color:#c0392b'>{text}</span>"


def placeholder_html(text: str) -> str:
    return (f'<div class="gsmn-maps" data-episode="" data-step="" style="padding:12px;font-size:13px;opacity:.7">'
            f"{html.escape(text)}</div>")


def other_side(text: str, side: str) -> str:
    other = {"left": "right", "right": "left", "front": "back", "back": "front"}[side]
    return text.replace(f"{side} side", f"{other} side", 1)


def status_line(episode: Episode) -> str:
    flying = {"model": "the model", "mirror": "the model as a mirror ensemble (maps: the unmirrored copy's)"}.get(
        episode.policy, "the expert" + (" (the model watching)" if episode.checkpoint else ""))
    state = {"queued": "queued", "running": "flying", "paused": "paused", "finished": "finished",
             "cancelled": "stopped early", "failed": "failed"}[episode.status]
    text = (f"**Episode {episode.id}** ({state}): {flying} in environment {episode.env_id}, "
            f"\"{html.escape(episode.instruction)}\".")
    note = ambiguity_note(episode)
    if note:
        text += " " + note
    if episode.error:
        text += f" Error: {html.escape(episode.error)}"
    return text


def ambiguity_note(episode: Episode) -> str:
    """For an instruction whose noun phrase names several landmarks of the world: how many, and that only the
    ringed one is the goal (the instruction cannot say which; flying to another of the same name fails)."""
    instruction = episode.task.instruction
    if not instruction.ambiguous:
        return ""
    n = len(episode.task.world.landmarks_named(instruction.noun_phrase))
    return (f"*Ambiguous: {n} landmarks here are called \"{html.escape(instruction.noun_phrase)}\"; the goal is at "
            f"the ringed one, and ending at another of them counts as a failure.*")


def plural(name: str, n: int) -> str:
    if n == 1:
        return name
    return f"{n} {name}{'es' if name.endswith(('s', 'x', 'sh', 'ch')) else 's'}"


def world_summary(world) -> str:
    """"8 landmarks: box, cone, 2 palm trees, pyramid, rock, tent": the count and every landmark, names shared by
    several landmarks counted, so the names always add up to the count."""
    counts: dict[str, int] = {}
    for lm in world.landmarks:
        counts[lm.noun_phrase] = counts.get(lm.noun_phrase, 0) + 1
    names = ", ".join(plural(name, counts[name]) for name in sorted(counts))
    n = len(world.landmarks)
    return f"{n} landmark{'s' if n != 1 else ''}: {html.escape(names)}"


def which_landmark(world, instruction) -> str:
    """For an ambiguous instruction: which of the landmarks of that name it means (the first in the world's list;
    the instruction cannot say), where it is, and how it is marked."""
    same = world.landmarks_named(instruction.noun_phrase)
    lm = world.landmarks[instruction.landmark_index]
    dist = math.hypot(lm.x - world.start_x, lm.y - world.start_y)
    return (f"ambiguous: {len(same)} are called \"{html.escape(instruction.noun_phrase)}\"; it means the one at "
            f"x {lm.x:.0f} m, y {lm.y:.0f} m, {dist:.0f} m from the start, drawn with its four sides")


def side_help(world, instruction) -> str:
    """What left, right, front and back mean (gsmn.task.metrics.side_of), for the landmark the text names."""
    return ("Sides are seen from the start (the white line in the 3D view): **front** faces it, **back** is beyond "
            f"the {html.escape(instruction.noun_phrase)}, **left** and **right** as you look from there.")


def parse_env_id(text) -> int:
    """The environment id typed in the page: a whole number from 0 to 2^31 - 1; ValueError with a message for people
    otherwise ("-5" and "abc" are refused, never turned into 0)."""
    raw = str(text).strip()
    if not raw.isdigit():
        raise ValueError(f"the environment id must be a whole number from 0 up (id % 100: 0-69 train, 70-84 test, "
                         f"85-99 dev), not \"{raw[:40]}\"")
    value = int(raw)
    if value > MAX_ENV_ID:
        raise ValueError(f"the environment id must be at most {MAX_ENV_ID}")
    return value


def instruction_parts(text: str, world) -> tuple[str | None, str | None]:
    """The side and the landmark name of this world that a (partial) instruction already holds, if any, as
    `gsmn.task.understand` reads them ("behind the tank" holds the back side and the tank)."""
    from gsmn.task.understand import understand

    u = understand(text or "", world)
    names = {lm.noun_phrase for lm in world.landmarks}
    return u.side, u.landmark if u.landmark in names else None


def suggestions(text: str, world, understood=None) -> tuple[str, ...]:
    """The landmark names of this world to offer under the instruction box: the candidates where several kinds fit
    what is typed ("the tree" with a fir tree and a palm tree), those starting with the word being typed (after
    "of the"), else all of them, sorted."""
    from gsmn.task.instructions import tokenize
    from gsmn.task.understand import understand

    candidates = (understood or understand(text or "", world)).candidates  # the caller's reading, if it has one
    if candidates:
        return tuple(c.noun_phrase for c in candidates)
    names = sorted({lm.noun_phrase for lm in world.landmarks})
    tokens = tokenize(text or "")
    tail = text.rstrip() == text and tokens and not text.endswith(" ")
    if tail:
        for k in (2, 1):  # "palm t" -> "palm tree"
            prefix = " ".join(tokens[-k:])
            matching = [n for n in names if n.startswith(prefix) and n != prefix]
            if matching:
                return tuple(matching)
    return tuple(names)


def compose_instruction(text: str, world, side: str | None = None, name: str | None = None) -> str:
    """The template "go to the {side} side of the {name}" filled from what is typed, with `side` or `name` (a chip
    or a landmark clicked in the scene) put in; a part not known yet stays a placeholder word the parser names."""
    from gsmn.task.instructions import TEMPLATE

    typed_side, typed_name = instruction_parts(text, world)
    return TEMPLATE.format(side=side or typed_side or "left", noun_phrase=name or typed_name or
                           sorted({lm.noun_phrase for lm in world.landmarks})[0])


def result_markdown(episode: Episode, success_radius: float = 6.0) -> str:
    """The outcome, plainly: success, distances, steps, how it ended, whether a failure flew through the success
    region, the final STOP probability."""
    r = episode.result
    if episode.status != FINISHED or r is None:
        n = len(episode.steps)
        where = f"at step {n - 1}, the timeline's last" if n else "before its first step"
        return f"#### Stopped early\nEpisode {episode.id} {episode.status} {where}." \
            + (f" {html.escape(episode.error)}" if episode.error else "")
    instruction = episode.task.instruction
    verdict = "Success" if r.success else "Failure"
    colour = "#1e8449" if r.success else "#c0392b"
    how = "said STOP" if r.stopped else f"ran out of steps (horizon {episode.horizon})"
    region = "inside" if r.landmark_success else "outside"
    stop = f"{r.stop_probability:.2f}" if r.stop_probability is not None else "n/a (no model)"
    note = ambiguity_note(episode)
    ambiguous = f"| ambiguous | {note} |\n" if note else ""
    passed = "" if r.success else f"| success region | {region_passage(episode, success_radius)} |\n"
    edited = f"| world edited | {html.escape(edits_text(episode))} |\n" if episode.world_edits else ""
    if episode.intervention is not None:
        edited += f"| map changed | {html.escape(intervention_text(episode))} |\n"
    return (f"#### Episode {episode.id}: <span style='color:{colour}'>{verdict}</span>\n"
            f"| | |\n|---|---|\n"
            f"| ended | {how} after **{r.steps}** steps |\n"
            f"| distance to goal | **{r.goal_distance:.1f} m** |\n"
            f"| distance to the {html.escape(instruction.noun_phrase)} | {r.landmark_distance:.1f} m ({region} the "
            f"{success_radius:g} m region) |\n"
            f"| quadrant | {quadrant_text(r, instruction.side)} |\n"
            f"{passed}"
            f"{ambiguous}"
            f"{edited}"
            f"| P(stop) at the end | {stop} |\n")


def edits_text(episode: Episode) -> str:
    """What the episode's world edits changed, in words ("moved landmark 2 to (12.0, 20.5); removed landmark 4";
    landmarks by their index in the environment's world), and the step of a fork that made them."""
    words = {"move": "moved landmark {landmark} to ({x:.1f}, {y:.1f})", "remove": "removed landmark {landmark}",
             "add": "added a {noun_phrase} at ({x:.1f}, {y:.1f})"}
    said = "; ".join(words[e.op].format(**e.to_dict()) for e in episode.world_edits)
    return said + (f", at step {episode.fork.step}" if episode.fork is not None else "")


def intervention_text(episode: Episode) -> str:
    """The map intervention the model flew with, in words, and the step it began ("perfect goal: the true goal
    map, held at every step, from step 12")."""
    since = f", from step {episode.fork.step}" if episode.fork is not None else ""
    return episode.intervention.describe() + since


def quadrant_text(r, asked: str) -> str:
    """Where it ended around the landmark, and the side asked: "stopped" only when it said STOP."""
    if r.stopped:
        return f"stopped **{r.final_side}**, asked **{asked}**"
    where = "" if r.landmark_success else ", outside the region"
    return f"ended **{r.final_side}**{where} without a STOP, asked **{asked}**"


def steps_in_region(episode: Episode, success_radius: float = 6.0) -> list[int]:
    """The episode's steps so far at which a STOP would have succeeded (`steps_in_success_region`)."""
    task = episode.task
    landmark = task.world.landmarks[task.instruction.landmark_index]
    return steps_in_success_region([s.position for s in list(episode.steps)], landmark.position,
                                   task.world.start_position, task.instruction.side, success_radius)


def region_passage(episode: Episode, success_radius: float = 6.0) -> str:
    """For a failed episode: whether the drone ever flew through the success region (where STOP would have
    succeeded), at which steps, and the model's highest P(stop) there. Telling a stopping failure from a
    navigation failure is the first question about a failure of a model that flies well."""
    inside = steps_in_region(episode, success_radius)
    steps = episode.steps
    probabilities = [p for i in inside if (p := steps[i].decisive_stop_probability) is not None]
    return region_text(inside, max(probabilities) if probabilities else None)


def region_text(inside: list[int], highest_stop: float | None = None, bold: tuple[str, str] = ("**", "**")) -> str:
    """The success-region row's text (live view and failure browser alike): "never entered", or the spans of
    steps inside the region and the model's highest P(stop) there when known (in `bold`: Markdown's by default,
    ("<b>", "</b>") for HTML)."""
    if not inside:
        return "never entered"
    spans, first = [], inside[0]
    for a, b in zip(inside, inside[1:] + [None], strict=True):
        if b != a + 1:
            spans.append(f"{first}" if first == a else f"{first}-{a}")
            first = b
    highest = f"; highest P(stop) there {bold[0]}{highest_stop:.2f}{bold[1]}" if highest_stop is not None else ""
    return (f"flew through it at step{'s' if len(inside) > 1 else ''} {', '.join(spans)} without a STOP there"
            f"{highest}")


def readout_markdown(episode: Episode, t: int, counterfactual, whatif_text: str | None) -> str:
    record = episode.steps[t]
    head = (f"**Step {t}** of {len(episode.steps) - 1}{' (live)' if episode.live else ''} · "
            f"{record.time:.1f} s · flown: v {record.v:.2f} m/s, ω {record.omega:+.2f} rad/s"
            f"{' · **STOP**' if record.stop else ''}")
    m = record.maps
    if m is not None:
        head += f"  \nmodel: v {m.v:.2f} m/s, ω {m.omega:+.2f} rad/s, **P(stop) {m.stop_probability:.2f}**"
    if whatif_text and counterfactual is None:
        head += "  \nwhat-if: grounding..."
    return head


def whatif_markdown(g: Grounding, record: StepRecord) -> str:
    own = record.maps
    compare = (f" (the episode's own instruction: v {own.v:.2f}, ω {own.omega:+.2f}, P(stop) "
               f"{own.stop_probability:.2f})") if own else ""
    return (f"**What if \"{html.escape(g.instruction.text)}\"** at step {g.step}: the model would fly v **{g.v:.2f}** "
            f"m/s, ω **{g.omega:+.2f}** rad/s, P(stop) **{g.stop_probability:.2f}**{compare}. Grounded in "
            f"{1000 * g.seconds:.1f} ms on the map already built; gold marks its goal and quadrant.")


TIMELINE_PX = 130.0  # the timeline slider's track in the 330-pixel control panel (measured in Chromium)
MARK_CHAR_PX = 4.2  # a character of a mark's label (viser's slider marks: 34 px for "in region")
MARK_GAP_PX = 4.0


def marks_clash(a: tuple[int, str | None], b: tuple[int, str | None], last: int) -> bool:
    """Whether two labelled marks, each centred on its step, would print over each other on the slider."""
    if a[1] is None or b[1] is None:
        return False
    apart = abs(a[0] - b[0]) / max(last, 1) * TIMELINE_PX
    return apart < MARK_CHAR_PX * (len(a[1]) + len(b[1])) / 2 + MARK_GAP_PX


def timeline_marks(episode: Episode, success_radius: float = 6.0) -> tuple[tuple[int, str | None], ...]:
    """Marks on the timeline: the ends, the first step inside the success region (where a STOP would have
    succeeded), and the first step where the model's P(stop) passed 0.5. Labels are centred on their step, so
    two whose text would meet on the slider (`marks_clash`, from the labels' widths) cannot both print: two
    inner marks share one label, and an end beside an inner label keeps its tick without its number (label
    None; the step box beside the slider shows it)."""
    steps = list(episode.steps)
    last = max(len(steps) - 1, 1)
    inside = steps_in_region(episode, success_radius)
    stop = next((s.step for s in steps if (s.decisive_stop_probability or 0.0) > 0.5), None)
    inner = [(t, label) for t, label in ((inside[0] if inside else None, "in region"), (stop, "P(stop)>0.5"))
             if t is not None and 0 < t < last]
    inner.sort(key=lambda mark: mark[0])  # stable: at one step, "in region" first
    if len(inner) == 2 and marks_clash(inner[0], inner[1], last):
        (a, first), (b, second) = inner
        inner = [(a, f"{first}, {second}")] + ([(b, None)] if b != a else [])
    ends = []
    for t in (0, last):
        mark = (t, str(t))
        ends.append((t, None) if any(marks_clash(mark, m, last) or m[0] == t for m in inner) else mark)
    return tuple(sorted(ends + inner, key=lambda mark: mark[0]))


ACTIONS_SERIES = (
    {"label": "step"},
    {"label": "v (m/s)", "stroke": "#2870f5", "width": 2},
    {"label": "omega (rad/s)", "stroke": "#e08020", "width": 2},
    {"label": "P(stop)", "stroke": "#d03030", "width": 2, "dash": [4, 3]},
    {"label": "STOP at 0.5", "stroke": "#888888", "width": 1, "dash": [2, 4]},
    {"label": "in success region", "stroke": "rgba(60,200,90,0)", "width": 0, "fill": "rgba(60,200,90,0.22)",
     "scale": "band", "spanGaps": False},
    {"label": "shown step", "stroke": "#222222", "width": 2, "scale": "band", "spanGaps": False},
)
ACTIONS_SCALES = {"x": {"time": False}, "band": {"auto": False, "range": (0.0, 1.0)}}
ACTIONS_AXES = ({"label": "step"}, {"label": "m/s, rad/s, P(stop)"})
CURSOR_HALF_WIDTH = 1e-3  # steps: the cursor is drawn as a spike over this much of the x axis


def actions_data(episode: Episode, cursor: int, success_radius: float = 6.0) -> tuple[np.ndarray, ...]:
    """The Actions plot's columns (`ACTIONS_SERIES`): v, omega and the P(stop) that decided each step, the 0.5 STOP
    line, a band over the steps inside the success region, and the shown step as a vertical line.

    uPlot draws series over one shared x, so the cursor is a spike (0, 1, 0 on its own 0-1 scale) over two extra x
    values just either side of the cursor's step, where the other series repeat that step's values."""
    steps = list(episode.steps)
    n = len(steps)
    x = np.arange(n, dtype=np.float64)
    v = np.array([s.v for s in steps], np.float64)
    omega = np.array([s.omega for s in steps], np.float64)
    stop = np.array([np.nan if (p := s.decisive_stop_probability) is None else p for s in steps], np.float64)
    band = np.full(n, np.nan)
    band[steps_in_region(episode, success_radius)] = 1.0
    t = max(0, min(cursor, n - 1))
    at = np.array([t, t + 1])  # insert before t and after it
    xs = np.insert(x, at, (t - CURSOR_HALF_WIDTH, t + CURSOR_HALF_WIDTH))

    def spread(column: np.ndarray) -> np.ndarray:
        return np.insert(column, at, (column[t], column[t]))

    line = np.full(len(xs), np.nan)
    line[t:t + 3] = (0.0, 1.0, 0.0)
    return xs, spread(v), spread(omega), spread(stop), np.full(len(xs), 0.5), spread(band), line


def inspector_markdown(report: CellReport | None, step: int) -> str:
    if report is None:
        return "That point is outside the map."
    classes = ", ".join(f"{html.escape(name)} {p:.2f}" for name, p in report.classes) or \
        "no landmark classes (trained without J_percept)"
    seen = "" if report.observed else " (not seen yet)"
    truth = f"**{html.escape(report.truth)}**" if report.truth else "open ground"
    goal = "no P(goal) (trained without J_plan)" if math.isnan(report.p_goal) else f"P(goal) **{report.p_goal:.2f}**"
    channels = ", ".join(f"{v:.2f}" for v in report.relevance)
    named = f"no P(named) (trained without J_ground), relevance channels {channels}" if math.isnan(report.p_named) \
        else f"P(named) **{report.p_named:.2f}**"
    return (f"**Cell ({report.row}, {report.col})** at x {report.x:.1f} m, y {report.y:.1f} m, step {step}{seen}: "
            f"perception {classes}; {named}, {goal}; "
            f"truly there: {truth}.")


# A world map clicked reads its cell as a click on the field does: the script types "row,col#time" into the hidden
# field CELL_FIELD (the page's `app.page.controls`), whose update reaches the server with its client.
CELL_FIELD = "gsmn-cell"


def _field_input(field: str) -> str:
    """JavaScript: `i`, the input of the viser text field labelled `field` (return where there is none yet)."""
    return ("var l=[].slice.call(document.querySelectorAll('label')).find(function(x){return x.textContent.trim()"
            "=='" + field + "'});if(!l)return;var i=(l.closest('.mantine-Flex-root')||l.parentElement)"
            ".querySelector('input');")


def typing_script(field: str, value_js: str) -> str:
    """An onclick script that types the JavaScript expression `value_js` (and the time, so a second click on the same
    thing is news too) into the hidden field `field`, whose update reaches the server with its client."""
    return ("var v=" + value_js + ";(function(){" + _field_input(field) + "var s=Object.getOwnPropertyDescriptor("
            "HTMLInputElement.prototype,'value').set;s.call(i,v+'#'+Date.now());i.dispatchEvent(new Event('input',"
            "{bubbles:true}));i.dispatchEvent(new Event('change',{bubbles:true}));})();")


def hide_field_html(field: str) -> str:
    """An invisible image whose script hides the text field `field` once the page has drawn it."""
    return ("<img src='data:,' alt='' style='display:none' onerror=\"var f=function(n){var l=[].slice.call("
            "document.querySelectorAll('label')).find(function(x){return x.textContent.trim()=='" + field +
            "'});if(!l){if(n<100)setTimeout(function(){f(n+1)},200);return;}(l.closest('.mantine-Flex-root')"
            "||l.parentElement).style.display='none';};f(0);\">")


CELL_CLICK = ("var b=this.getBoundingClientRect(),n=+this.dataset.cells,r=Math.floor((event.clientY-b.top)/b.height*n),"
              "c=Math.floor((event.clientX-b.left)/b.width*n);" + typing_script(CELL_FIELD, "r+','+c"))
HIDE_CELL_FIELD = hide_field_html(CELL_FIELD)


def parse_cell_click(value: str, cells: int) -> tuple[int, int] | None:
    """The (row, col) a map click typed into CELL_FIELD ("12,30#1712345678"), None for anything else."""
    try:
        r, c = (int(v) for v in value.split("#", 1)[0].split(","))
    except ValueError:
        return None
    return (r, c) if 0 <= r < cells and 0 <= c < cells else None


def cell_marks_html(cells: list[tuple[int, int, tuple[int, int, int]]], size: int) -> str:
    """Outlines of cells (row, col, colour) over a size x size map drawn at any scale (positions in percent)."""
    step = 100 / size
    return "".join(f'<div style="position:absolute;left:{c * step:.3f}%;top:{r * step:.3f}%;width:{step:.3f}%;'
                   f'height:{step:.3f}%;box-shadow:inset 0 0 0 1px rgb({colour[0]},{colour[1]},{colour[2]})"></div>'
                   for r, c, colour in cells if 0 <= r < size and 0 <= c < size)


# On a short screen (1280 x 800) the camera and the four map panels must fit the panel's height with the tab bar
# and the readout: the camera at most 23 % of the window's height, each map (a square) at most 18 % (the six tabs
# take two rows of the panel's 420 px, and the semantic map's legend up to five lines).
CAMERA_MAX_HEIGHT, MAP_MAX_HEIGHT = "23vh", "18vh"


def camera_html(jpeg: bytes) -> str:
    """The camera panel: the recorded JPEG (256 x 144), scaled to the panel's width (at most CAMERA_MAX_HEIGHT
    high) with its pixels sharp."""
    return (f'<div style="padding-right:10px"><img class="gsmn-camera" '
            f'src="data:image/jpeg;base64,{base64.b64encode(jpeg).decode("ascii")}" '
            f'style="{PIXELATED};max-height:{CAMERA_MAX_HEIGHT};object-fit:contain;border-radius:3px"/></div>')


def maps_html(episode: Episode, t: int, layers: dict[str, Layer] | None, whatif_text: str | None,
              cell_of, beside: dict[str, str] | None = None, line: str = "") -> str:
    """The map panels of one step, one per layer (`app.render.layers.map_layers`: semantic, relevance and goal north-up,
    the robot-frame goal map, then the record's other maps), each with its legend. The drone's cell is outlined in
    white and the goal's in red on the world maps. `beside`: a panel to put to the right of a layer's, by its name
    (the ground truth of that map; the maps with one then go first, one pair a row); `line`: a line under them."""
    attrs = (f'class="gsmn-maps" data-episode="{episode.id}" data-step="{t}" '
             f'data-counterfactual="{int(bool(whatif_text))}"')
    if layers is None:
        return (f'<div {attrs} style="padding:12px;font-size:13px;opacity:.7">No model maps for this episode: '
                f"the expert flew without a checkpoint loaded.</div>")
    record = episode.steps[t]
    instruction = episode.task.instruction
    marks = [(*cell_of(record.position[0], record.position[1]), (255, 255, 255)),
             (*cell_of(instruction.goal_x, instruction.goal_y), (230, 30, 30))]
    cells = []
    beside = beside or {}
    paired = [n for n in layers if n in beside]
    for name in paired + [n for n in layers if n not in beside]:  # the pairs first: each one a row of the grid
        layer = layers[name]
        overlay = cell_marks_html(marks, layer.rgb.shape[0]) if layer.frame == "world" else ""
        title = layer.title
        if whatif_text and name in WHATIF_LAYERS:
            title += " · what-if"
        orient = ORIENTATIONS[layer.frame]
        click = f' onclick="{CELL_CLICK}"' if layer.frame == "world" else ""
        box = f"position:relative;border-radius:3px;overflow:hidden;width:min(100%,{MAP_MAX_HEIGHT});aspect-ratio:1" + (
            ";cursor:crosshair" if layer.frame == "world" else "")
        cells.append(f'<div><div style="font-weight:600;font-size:12px;line-height:1.2;margin-bottom:2px">'
                     f'{html.escape(title)}</div>'
                     f'<div style="{box}"{click} data-cells="{layer.rgb.shape[0]}">'
                     f'<img data-layer="{name}" src="{data_uri(png_bytes(layer.rgb))}" style="{PIXELATED};height:100%" '
                     f'title="{orient}"/>{overlay}</div>{glossed(layer.legend_html)}</div>')
        if name in beside:
            cells.append(beside[name])
    caption = line + (f"<div style='font-size:11px;opacity:.75;margin-top:4px'>Step {t}. World maps north up, 0.94 m "
                      f"cells; white: the drone's cell, red: the goal.</div>")
    if whatif_text:
        caption += (f"<div style='font-size:11px;color:#9a6b00'>Relevance and goal grounded for what-if "
                    f"\"{html.escape(whatif_text)}\".</div>")
    grid = "display:grid;grid-template-columns:repeat(2,minmax(0,1fr));gap:8px"
    return f'<div {attrs} style="padding-right:10px"><div style="{grid}">{"".join(cells)}</div>{caption}</div>'
