"""Drawing one tab's shown step (its UI thread): the scene's drone, path and map layers, the camera, readout, maps
and inspector panels, the timeline and the Actions plot, and the counterfactual grounded on the shown step's map.
"""


from __future__ import annotations

import html
import time
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout

import numpy as np
from viser._messages import GuiSliderMark

from app.live.commands import (
    Ground,
    Grounding,
)
from app.live.recording import Episode, StepRecord
from app.page.controls import INSPECT_HINT, SEMANTIC_READINGS
from app.page.events import (
    Grounded,
)
from app.render.glossary import glossed
from app.render.layers import inspect_cell, map_layers
from app.render.panels import (
    actions_data,
    camera_html,
    error_html,
    inspector_markdown,
    maps_html,
    readout_markdown,
    result_markdown,
    timeline_marks,
    whatif_markdown,
)
from app.render.truth import result_rows
from gsmn.task.instructions import InstructionError
from gsmn.task.understand import parse_instruction

GROUNDING_WAIT = 0.25  # s the page waits for a counterfactual grounding before drawing without it


class ViewerDrawing:
    """The drawing part of `app.page.viewer.Viewer` (what it draws is the viewer's `view` and GUI handles)."""

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
            layers = map_layers(maps, heads, self.value_mode.value, self.range_mode.value, *self.world_reading(episode))
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
        self.readout.content = glossed(readout_markdown(episode, t, counterfactual, self.view.counterfactual))
        beside, line = self.compare.truth_cells(episode, t)
        self.maps.content = maps_html(episode, t, layers, self.view.counterfactual if grounding else None,
                                      self._cell_of, beside, line)
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

    def forget_cell(self) -> None:
        """Another world: no cell inspected, its outline and its reading gone (they were of the world before)."""
        self.scene.mark_cell(None, 1.0)
        self.view.inspected = None
        self.inspector.content = INSPECT_HINT

    def world_reading(self, episode: Episode) -> tuple[tuple[str, ...], str]:
        """The episode's world's landmark names and the semantic reading chosen: how every map panel reads the
        semantic map (the comparison's second set too)."""
        return (tuple(lm.noun_phrase for lm in episode.task.world.landmarks),
                SEMANTIC_READINGS[self.semantic_reading.value])

    def show_result(self, episode: Episode) -> None:
        """The result table of an episode that ended, with its maps' agreement with the truth."""
        model = self.runner.models.get(episode.checkpoint) if episode.checkpoint else None
        radius = self.runner.config.task.success_radius
        self.result.content = glossed(result_markdown(episode, radius) + result_rows(
            episode, model.heads if model else None, radius))

    def _inspect(self, episode: Episode, record: StepRecord, grounding: Grounding | None) -> None:
        xy, model = self.view.inspected, self.runner.models.get(episode.checkpoint) if episode.checkpoint else None
        if xy is None:
            return
        world = episode.task.world
        # a click's reading is also a notification: the readout lies under the maps, often out of view
        announce, self.announce_cell = self.announce_cell, False
        with self.client.atomic():
            self.scene.mark_cell(xy, world.field_size / self.runner.config.model.map_size)
        if record.maps is None or model is None:
            self.inspector.content = "No model maps to inspect in this episode."
            return
        m = record.maps
        report = inspect_cell(xy[0], xy[1], m.semantic_w, grounding.relevance_w if grounding else m.relevance_w,
                              grounding.goal_w if grounding else m.goal_w, model.heads, world)
        self.inspector.content = glossed(inspector_markdown(report, record.step))
        if announce:
            self.client.add_notification("Map cell", inspector_markdown(report, record.step).replace("**", ""),
                                         auto_close_seconds=10.0)

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
