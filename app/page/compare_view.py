"""The page's comparisons, forks and ground truth (`app.live.compare`, `app.render.truth`), beside the live view of
`app.page.viewer`.

- **Compare and fork** (a folder of the controls): *Compare with* another policy (and optionally its own
  instruction) and **Run both**: the two fly the shown environment together; **Fork here** flies on from the step
  the timeline shows, with the instruction and policy typed there (empty: the original's).
- **The other drone**: while the shown episode is one side of a comparison, or a fork, the other side (the
  comparison's second episode, or the fork's original) is drawn in the scene in magenta, its drone, camera frustum
  and path, at the same step as the timeline (one slider scrubs both); a fork's own path starts at its fork point.
  The *Comparison* tab shows its camera image and map panels at that step, both results side by side, which one
  succeeded, and the step at which they part (`app.live.compare.diverged_at`), also marked in the scene by a ring.
- **Ground truth**: *Truth beside the maps* adds the three truth layers (`app.render.truth`) under the model's map
  panels with the step's agreement figures; the *Actions* tab plots the figures over the episode beside P(stop).
"""

from __future__ import annotations

import base64
import html
from pathlib import Path

import numpy as np
import viser

from app.live.compare import ForkEpisode, PolicySpec, StartComparison, diverged_at
from app.live.recording import Episode
from app.page.scene import R_to_wxyz, _has, _segments, yaw_wxyz
from app.render.colors import data_uri, png_bytes
from app.render.glossary import glossed
from app.render.layers import map_layers
from app.render.panels import MAP_MAX_HEIGHT, PIXELATED, maps_html
from app.render.truth import (
    TRUTH_LAYERS,
    TRUTH_TITLES,
    episode_truth,
    step_figures,
    truth_rgb,
    went_wrong,
    went_wrong_text,
)
from gsmn.analysis.intervention import Intervention, InterventionError, paint_from_text, parse_intervention
from gsmn.task.edits import EditError, edits_from_text
from gsmn.world.spec import world_for_env

PARTNER_RGB = (200, 40, 200)
AS_ORIGINAL = "As the original"
FORK_MAPS = ("The model's own", "Perfect perception", "Perfect grounding", "Perfect goal", "Painted goal map",
             "Painted relevance map")


def fork_intervention(choice: str, paint: str) -> Intervention | None:
    """The map intervention the fork controls ask for (`gsmn.analysis.intervention`), or None for the model's own
    maps; InterventionError says what is wrong."""
    if choice == FORK_MAPS[0]:
        return None
    if choice.startswith("Painted"):
        return parse_intervention({"map": choice.split()[1], "with": "painted", "paint": paint_from_text(paint)})
    return parse_intervention({"map": {"perception": "semantic", "grounding": "relevance", "goal": "goal"}[
        choice.split()[1]]})


def who_flew(e: Episode, models: dict) -> str:
    """Who flew an episode, in words: the expert, or the model by its checkpoint's name (and whether it flew as a
    mirror ensemble). `models`: the runner's loaded models by resolved path."""
    if e.policy == "expert":
        return "expert"
    m = models.get(e.checkpoint) if e.checkpoint else None
    name = m.name if m is not None else (e.checkpoint or "?")
    if Path(name).is_absolute():  # a folder outside checkpoints/: its last part
        name = Path(name).name
    return f"model {name}" + (", mirror ensemble" if e.policy == "mirror" else "")


def step_words(t: int, shown: int) -> str:
    """'step 12', or what it is when the timeline (at `t`) is past the episode's last step `shown`."""
    return f"step {shown}" if shown == t else f"step {shown}, its last (it ended before step {t})"


def cameras_html(jpeg_a: bytes, jpeg_b: bytes, step_a: int, step_b: int, caption_a: str = "",
                 caption_b: str = "") -> str:
    """Both camera images side by side, the shown episode's (blue) first, each captioned with whose it is."""
    def one(jpeg: bytes, colour: str, cls: str, step: int, caption: str) -> str:
        src = "data:image/jpeg;base64," + base64.b64encode(jpeg).decode("ascii")
        return (f'<div><img class="{cls}" data-step="{step}" src="{src}" style="{PIXELATED};border-radius:3px;'
                f'border:3px solid {colour}"/><div class="{cls}-caption" style="font-size:12px;color:{colour}">'
                f"{html.escape(caption)}</div></div>")

    return (f'<div style="display:grid;grid-template-columns:1fr 1fr;gap:6px;padding-right:10px">'
            f'{one(jpeg_a, "#2870f5", "gsmn-camera-a", step_a, caption_a)}'
            f'{one(jpeg_b, "#c828c8", "gsmn-camera-b", step_b, caption_b)}</div>')


def clear_of(marks: tuple, step: int, steps: int, room: float = 0.25) -> tuple:
    """The timeline's marks that leave room for a label at `step`: a mark nearer than `room` of the timeline goes, the
    first and last steps' keep their tick without their number (a label is about a quarter of the slider wide in a
    1280-pixel window)."""
    ends = (0, max(steps - 1, 1))
    near = [m for m in marks if m[0] != step and abs(m[0] - step) < room * steps]
    return tuple(m for m in marks if m[0] != step and m not in near) + tuple((m[0], "") for m in near
                                                                              if m[0] in ends)


class CompareView:
    def __init__(self, viewer):
        self.viewer = viewer
        self.partner_drawn = False
        self.partner_nodes: tuple | None = None  # the other drone's frustum and body, once drawn
        self.plot_steps = -1

    # -- building ---------------------------------------------------------------------------------------------
    def build_controls(self, gui) -> None:
        v = self.viewer
        choices = v._policy_choices()
        with gui.add_folder("Compare and fork", expand_by_default=False):
            self.other = gui.add_dropdown("Compare with", choices, initial_value=choices[-1],
                                          hint="the second policy; both fly the environment shown, together")
            self.other_mirror = gui.add_checkbox("Its mirror ensemble", False,
                                                 hint="fly that model as a mirror ensemble (the box above is for "
                                                      "the first policy): the model plain against its ensemble")
            self.other_instruction = gui.add_text("Its instruction", "", hint="empty: the instruction above")
            self.compare_button = gui.add_button("Run both", icon=viser.Icon.ARROWS_SPLIT,
                                                 hint="fly the policy above and this one side by side")
            self.fork_instruction = gui.add_text("Fork instruction", "", hint="empty: the original's")
            self.fork_policy = gui.add_dropdown("Fork policy", (AS_ORIGINAL, *choices), initial_value=AS_ORIGINAL)
            self.fork_map = gui.add_dropdown("Fork maps", FORK_MAPS, initial_value=FORK_MAPS[0],
                                             hint="fly on with a corrected map in place of the model's own: the "
                                                  "ground truth, or its own map with paint (below)")
            self.fork_paint = gui.add_text("Paint", "", hint="for a painted map: 'peak 12 20; erase 5 5 2' (x y "
                                                             "[radius], metres)")
            self.fork_button = gui.add_button("Fork here", icon=viser.Icon.GIT_FORK,
                                              hint="fly on from the step shown, from the simulator's exact state "
                                                   "there (with the World edits above made at that step)")
            self.note = gui.add_markdown("")
        self.truth_box = gui.add_checkbox("Truth beside the maps", False,
                                          hint="the true landmarks, the named landmark and the success region under "
                                               "the map panels, with how well each map agrees")
        self.compare_button.on_click(lambda _: self._compare())
        self.fork_button.on_click(lambda _: self._fork())
        from app.page.events import OptionsChanged

        self.truth_box.on_update(lambda _: v._events.put(OptionsChanged()))

    def build_tab(self, panel, gui) -> None:
        with panel.add_tab("Comparison", viser.Icon.ARROWS_SPLIT):
            self.summary = gui.add_markdown("Run two policies side by side (*Compare and fork*, left), or fork an "
                                            "episode: the other drone shows here.")
            self.partner_camera = gui.add_html("")
            self.partner_maps = gui.add_html("")

    def build_plot(self, gui) -> None:
        self.figures_plot = gui.add_uplot(
            data=(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1)),
            series=({"label": "step"}, {"label": "perception", "stroke": "#8e44ad", "width": 2},
                    {"label": "relevance AUC", "stroke": "#16a085", "width": 2},
                    {"label": "goal mass", "stroke": "#e08020", "width": 2},
                    {"label": "P(stop)", "stroke": "#d03030", "width": 2, "dash": [4, 3]}),
            title="The maps against the ground truth, and P(stop)", aspect=1.4,
            scales={"x": {"time": False}, "y": {"auto": False, "range": [0, 1]}}, axes=({"label": "step"}, {}))

    # -- callbacks --------------------------------------------------------------------------------------------
    def _compare(self) -> None:
        from app.page.events import StartAnswered

        v = self.viewer
        policy, checkpoint = v._policy_of_choice()
        other = self.other.value
        other_policy, other_checkpoint = ("expert", None) if not other.startswith("Model: ") else (
            "mirror" if self.other_mirror.value else "model", v.checkpoint_of(other))
        env_id = v._env_id()  # a typed id the page refuses ("-5", "abc") is said in the status line
        if env_id is None:
            return
        text = v.instruction.value.strip() or None
        specs = [PolicySpec(policy, checkpoint), PolicySpec(other_policy, other_checkpoint,
                                                            self.other_instruction.value.strip() or None)]
        self.note.content = "Starting both..."
        v._post(StartComparison(env_id, text, specs, preempt=True), StartAnswered)

    def _fork(self) -> None:
        from app.page.events import StartAnswered

        v = self.viewer
        episode = v.view.episode
        if episode is None or not episode.steps:
            self.note.content = "Run an episode first: a fork flies on from one of its steps."
            return
        choice = self.fork_policy.value
        policy = checkpoint = None
        if choice != AS_ORIGINAL:
            policy, checkpoint = ("expert", None) if not choice.startswith("Model: ") else (
                "mirror" if v.mirror.value else "model", v.checkpoint_of(choice))
        step = max(0, min(int(v.view.cursor), len(episode.steps) - 1))
        try:
            intervention = fork_intervention(self.fork_map.value, self.fork_paint.value)
            # the World edits box (Episode panel) applies to a fork too: made to the world at its step
            edits = edits_from_text(v.world_edits.value, world_for_env(episode.env_id, v.runner.config.world))
            edits = () if tuple(edits) == tuple(episode.world_edits) else edits  # the world it flew: as it was
        except (InterventionError, EditError) as e:
            self.note.content = f"**Not forked:** {html.escape(str(e))}"
            return
        self.note.content = f"Forking episode {episode.id} at step {step}..."
        v._post(ForkEpisode(episode.id, step, self.fork_instruction.value.strip() or None, checkpoint, policy,
                            preempt=True, world_edits=edits, intervention=intervention), StartAnswered)

    # -- which episodes go together ---------------------------------------------------------------------------
    def partner_of(self, episode: Episode | None) -> Episode | None:
        if episode is None:
            return None
        runner = self.viewer.runner
        if episode.comparison is not None:
            c = runner.comparison(episode.comparison)
            if c is not None:
                return next(e for e in c.episodes if e is not episode)
        if episode.fork is not None:
            return runner.episodes.get(episode.fork.episode_id)
        return None

    def keeps_shown(self, started: Episode) -> bool:
        """A comparison's second episode starting does not replace its first in the view."""
        shown = self.viewer.view.episode
        return (shown is not None and started is not shown and started.comparison is not None
                and shown.comparison == started.comparison)

    def is_partner(self, episode: Episode) -> bool:
        return episode is self.partner_of(self.viewer.view.episode)

    def own_path(self, episode: Episode, positions: np.ndarray) -> np.ndarray:
        """A fork's path starts at its fork point."""
        return positions[episode.fork.step:] if episode.fork is not None else positions

    def parting(self, episode: Episode, partner: Episode) -> int | None:
        return diverged_at([s.position for s in episode.steps], [s.stop for s in episode.steps], episode.live,
                           [s.position for s in partner.steps], [s.stop for s in partner.steps], partner.live)

    def with_parting(self, episode: Episode | None, marks: tuple) -> tuple:
        """The timeline's marks with the step at which the shown episode and its partner part ("parted")."""
        partner = self.partner_of(episode)
        part = self.parting(episode, partner) if partner is not None else None
        if part is None or not 0 < part < len(episode.steps) - 1:
            return marks
        return tuple(sorted((*clear_of(marks, part, len(episode.steps)), (part, "parted")), key=lambda m: m[0]))

    # -- drawing ----------------------------------------------------------------------------------------------
    def clear(self) -> None:
        """Take the other drone, its path and its panels away (another world, or an episode without a partner)."""
        if self.partner_drawn:
            for name in ("/partner", "/partner_flown", "/parted"):
                self.viewer.client.scene.remove_by_name(name)
            self.partner_drawn, self.partner_nodes = False, None
            self.summary.content = "No comparison shown: run two policies side by side, or fork an episode."
            self.partner_camera.content = self.partner_maps.content = ""
        if self.note.content.startswith("Showing"):  # "Showing fork 14 of episode 7": a pair no longer shown
            self.note.content = ""

    def _place_partner(self, record) -> None:
        """The other drone and its camera frustum at `record`: made once, then moved (as the drone is,
        app.page.scene.Scene.set_drone), so that it never shows for a frame where a new node starts, at the origin."""
        scene, s = self.viewer.client.scene, self.viewer.scene
        wxyz, position = R_to_wxyz(record.T_world_camera[:3, :3]), record.T_world_camera[:3, 3]
        if self.partner_nodes is None or not _has(scene, "/partner/camera") or not _has(scene, "/partner/body"):
            self.partner_nodes = (
                scene.add_camera_frustum("/partner/camera", fov=s.vfov, aspect=s.aspect, scale=1.6, thickness=0.05,
                                         image=None, wxyz=wxyz, position=position, color=PARTNER_RGB),
                scene.add_box("/partner/body", color=PARTNER_RGB, dimensions=(0.5, 0.36, 0.1),
                              wxyz=yaw_wxyz(record.yaw), position=record.position))
            return
        frustum, body = self.partner_nodes
        frustum.wxyz, frustum.position = wxyz, position
        body.wxyz, body.position = yaw_wxyz(record.yaw), record.position

    def render(self, episode: Episode, t: int) -> None:
        partner = self.partner_of(episode)
        scene = self.viewer.client.scene
        if partner is None or not partner.steps:
            self.clear()
            self._plot_figures(episode)
            return
        pt = max(0, min(t, len(partner.steps) - 1))
        record = partner.steps[pt]
        part = self.parting(episode, partner)
        path = np.array([s.position for s in partner.steps[: pt + 1]], np.float32)
        with self.viewer.client.atomic():
            self._place_partner(record)
            if len(path) >= 2:
                path[:, 2] = 0.16
                scene.add_line_segments("/partner_flown", _segments(path), PARTNER_RGB, thickness=0.2)
            if part is not None and part < len(episode.steps):
                x, y, _ = episode.steps[part].position
                scene.add_icosphere("/parted", radius=0.45, color=(250, 250, 250), position=(x, y, 0.3))
            elif self.partner_drawn:
                scene.remove_by_name("/parted")
        self.partner_drawn = True
        fork = episode.fork
        note = (f"Showing fork {episode.id} of episode {fork.episode_id} (from step {fork.step}) beside it."
                if fork is not None and fork.episode_id == partner.id else
                f"Showing episodes {episode.id} and {partner.id} side by side.")
        if self.note.content != note:
            self.note.content = note
        self.summary.content = self._summary(episode, partner, part, t)
        self._draw_partner_views(episode, partner, t, pt)
        self._plot_figures(episode)

    def _draw_partner_views(self, episode: Episode, partner: Episode, t: int, pt: int) -> None:
        """Both cameras, each saying whose it is and at which step, and the magenta episode's maps under a title
        that says the same (its last step where it ended before the timeline's)."""
        models = self.viewer.runner.models
        at = max(0, min(t, len(episode.steps) - 1))
        shown, record = episode.steps[at], partner.steps[pt]
        self.partner_camera.content = cameras_html(
            shown.camera_jpeg, record.camera_jpeg, at, pt,
            f"blue: episode {episode.id}, {who_flew(episode, models)}, {step_words(t, at)}",
            f"magenta: episode {partner.id}, {who_flew(partner, models)}, {step_words(t, pt)}")
        model = models.get(partner.checkpoint) if partner.checkpoint else None
        title = (f'<div class="gsmn-partner-title" style="font-size:13px;margin:6px 0 2px"><b style="color:#c828c8">'
                 f"Magenta's maps</b>: episode {partner.id}, {html.escape(who_flew(partner, models))}, "
                 f"{step_words(t, pt)}</div>")
        layers = None
        if record.maps is not None and model is not None:
            layers = map_layers(record.maps.maps, model.heads, self.viewer.value_mode.value,
                                self.viewer.range_mode.value, *self.viewer.world_reading(partner))
        self.partner_maps.content = title + maps_html(partner, pt, layers, None, self.viewer._cell_of).replace(
            'class="gsmn-maps"', 'class="gsmn-maps-partner"', 1)

    def _summary(self, episode: Episode, partner: Episode, part: int | None, t: int) -> str:
        def side(e: Episode, name: str) -> str:
            r = e.result
            if r is None:
                result = f"{e.status}, {len(e.steps)} steps so far"
            else:
                mark = "✓ success" if r.success else "✗ failure"
                ended = "STOP" if r.stopped else "horizon"
                result = f"{mark}: {ended} after {r.steps} steps, {r.goal_distance:.1f} m from the goal"
            who = html.escape(who_flew(e, self.viewer.runner.models))
            return (f"| **{name}** · {who} | episode {e.id}, \"{html.escape(e.instruction)}\" | {result} |")

        fork = episode.fork if episode.fork is not None and episode.fork.episode_id == partner.id else None
        title = (f"### Fork of episode {partner.id} at step {fork.step}" if fork else "### Side by side")
        rows = [side(episode, "blue (shown)"), side(partner, "magenta")]
        parted = ("They have not parted" + (" yet." if episode.live or partner.live else ".")) if part is None \
            else f"They part at step **{part}** (white ring), the timeline is at step {t}."
        done = [e for e in (episode, partner) if e.result is not None]
        if len(done) == 2:
            winners = [name for e, name in ((episode, "blue"), (partner, "magenta")) if e.result.success]
            parted += " Succeeded: " + (", ".join(winners) if winners else "neither") + "."
        return f"{title}\n| | | |\n|---|---|---|\n" + "\n".join(rows) + f"\n\n{parted}"

    def truth_cells(self, episode: Episode, t: int) -> tuple[dict[str, str], str]:
        """The truth panels with the step's figures, by the model map each stands beside ("semantic", "relevance",
        "goal"; `app.render.panels.maps_html` puts each to the right of its map), and the line under the maps;
        ({}, "") when off or without maps."""
        if not self.truth_box.value or not episode.steps or episode.steps[t].maps is None:
            return {}, ""
        model = self.viewer.runner.models.get(episode.checkpoint) if episode.checkpoint else None
        if model is None:
            return {}, ""
        radius = self.viewer.runner.config.task.success_radius
        truth = episode_truth(episode, episode.steps[t].maps.semantic_w.shape[-1], radius)
        figures = step_figures(episode, model.heads, radius)
        f = figures[t] if t < len(figures) else None

        def fmt(x):
            return "n/a" if x is None else f"{x:.2f}"

        values = {"truth_semantic": f"perception {fmt(f.perception) if f else 'n/a'}",
                  "truth_relevance": f"relevance AUC {fmt(f.relevance) if f else 'n/a'}",
                  "truth_goal": f"goal mass {fmt(f.goal) if f else 'n/a'}"}
        cells = {name.removeprefix("truth_"): (
            f'<div class="gsmn-truth" data-step="{t}"><div style="font-weight:600;font-size:12px;line-height:1.2;'
            f'margin-bottom:2px">{html.escape(TRUTH_TITLES[name])}</div>'
            f'<div style="border-radius:3px;overflow:hidden;width:min(100%,{MAP_MAX_HEIGHT});aspect-ratio:1">'
            f'<img data-layer="{name}" src="{data_uri(png_bytes(truth_rgb(name, truth, model.heads)))}" '
            f'style="{PIXELATED};height:100%"/></div><div class="gsmn-figure" data-figure="{name}" '
            f'style="font-size:11px">{glossed(values[name])}</div></div>') for name in TRUTH_LAYERS}
        wrong = glossed(went_wrong_text(went_wrong(figures[: t + 1], model.heads), ("<b>", "</b>")))
        return cells, f'<div class="gsmn-truth-line" style="font-size:11px;opacity:.8">Up to step {t}: {wrong}</div>'

    def _plot_figures(self, episode: Episode) -> None:
        n = len(episode.steps)
        if n == self.plot_steps or (episode.live and 0 < n - self.plot_steps < 5 and n >= 5):
            return
        self.plot_steps = n
        model = self.viewer.runner.models.get(episode.checkpoint) if episode.checkpoint else None
        figures = step_figures(episode, model.heads, self.viewer.runner.config.task.success_radius) \
            if model is not None else [None] * n
        figures = (figures + [None] * n)[:n]

        def col(name: str) -> np.ndarray:
            return np.array([np.nan if f is None or getattr(f, name) is None else getattr(f, name) for f in figures],
                            np.float64)

        stop = np.array([np.nan if (p := s.decisive_stop_probability) is None else p for s in episode.steps],
                        np.float64)
        self.figures_plot.data = (np.arange(n, dtype=np.float64), col("perception"), col("relevance"), col("goal"),
                                  stop)

    def reset_plot(self) -> None:
        self.plot_steps = -1
