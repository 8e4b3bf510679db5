"""Editing the world by picking in the 3D view (viser's callback threads; it changes the Episode panel's controls
only). With "Pick to edit" on, a landmark clicked is picked (instead of going into the instruction); then a click on
the ground moves it there, **Remove** removes it and **Add beside** puts a landmark of the catalogue next to it. Each
adds its words to the "World edits" box (`gsmn.task.edits.edits_from_text`), which **Run** flies; the box may be
typed in too. Edits name the landmarks of the environment's own world, so picking needs that world shown.
"""

from __future__ import annotations

import html
import math

from app.render.panels import error_html
from gsmn.task.edits import EditError, edit_world, edits_from_text
from gsmn.world.catalogue import CATALOGUE
from gsmn.world.spec import world_for_env

ADDABLE = tuple(sorted({m.noun_phrase for m in CATALOGUE}))
BESIDE = 4.5  # m between the picked landmark's centre and the added one's


class WorldEditPicker:
    """The "Pick to edit" controls under the World edits box of `controls` (`app.page.controls.Controls`)."""

    def __init__(self, controls, gui):
        self.controls = controls
        self.pick = gui.add_checkbox("Pick to edit", False, hint="click a landmark in the 3D view to pick it, then "
                                     "click the ground where it goes, or remove it, or add one beside it")
        self.note = gui.add_markdown("", visible=False)
        self.add_what = gui.add_dropdown("Add beside it", ADDABLE, initial_value="tank", visible=False)
        self.actions = gui.add_button_group("Picked", ("Remove", "Add beside"), visible=False)
        self.picked: int | None = None
        self.pick.on_update(lambda _: self._toggle())
        self.actions.on_click(lambda e: self._act(e.target.value))

    @property
    def picking(self) -> bool:
        return bool(self.pick.value)

    def show(self, visible: bool) -> None:
        """Shown or hidden with the World edits box (presenter mode hides both)."""
        self.pick.visible = visible
        for control in (self.note, self.add_what, self.actions):
            control.visible = visible and self.picking

    def _toggle(self) -> None:
        self.picked = None
        for control in (self.note, self.add_what, self.actions):
            control.visible = self.picking
        self.note.content = "Click a landmark in the 3D view." if self.picking else ""

    def _world(self):
        """The environment's own world when the scene shows it (the edits name its landmarks), else None."""
        shown = self.controls.world_shown
        if shown is None:
            return None
        own = world_for_env(shown.world.env_id, self.controls.runner.config.world)
        return own if shown.world == own else None

    def landmark_clicked(self, index: int) -> None:
        world = self._world()
        if world is None:
            self.note.content = error_html("The scene shows an edited world: press **Show** for the environment's own "
                                           "world, then pick its landmarks.")
            return
        self.picked = index
        lm = world.landmarks[index]
        self.note.content = (f"Picked **{html.escape(self._ref(world, index))}** at ({lm.x:.1f}, {lm.y:.1f}): click "
                             "the ground where it goes, or **Remove** it, or **Add beside** it.")

    def ground_clicked(self, x: float, y: float) -> bool:
        """A click on the ground moves the picked landmark there; False when nothing is picked (the click reads the
        maps' cell as usual)."""
        world = self._world()
        if not self.picking or self.picked is None or world is None:
            return False
        self._append(world, f"move {self._ref(world, self.picked)} to {x:.1f} {y:.1f}")
        return True

    def _act(self, action: str) -> None:
        world = self._world()
        if self.picked is None or world is None:
            self.note.content = "Pick a landmark in the 3D view first."
            return
        ref = self._ref(world, self.picked)
        if action == "Remove":
            self._append(world, f"remove {ref}")
            return
        lm, config = world.landmarks[self.picked], self.controls.runner.config
        for angle in range(0, 360, 30):  # the first place beside it where the new landmark may stand
            x = lm.x + BESIDE * math.cos(math.radians(angle))
            y = lm.y + BESIDE * math.sin(math.radians(angle))
            words = f"add {self.add_what.value} at {x:.1f} {y:.1f}"
            try:
                edit_world(world, edits_from_text(self._joined(words), world), config)
            except EditError:
                continue
            self._append(world, words)
            return
        self.note.content = error_html(f"No room for a {html.escape(self.add_what.value)} beside the "
                                       f"{html.escape(lm.noun_phrase)}: pick another landmark.")

    def _joined(self, words: str) -> str:
        typed = self.controls.world_edits.value.strip().rstrip(";")
        return f"{typed}; {words}" if typed else words

    def _append(self, world, words: str) -> None:
        """Add `words` to the World edits box, if the edits there and these still stand; else say why not."""
        text = self._joined(words)
        try:
            edit_world(world, edits_from_text(text, world), self.controls.runner.config)
        except EditError as e:
            self.note.content = error_html(f"**Not added:** {html.escape(str(e))}")
            return
        self.controls.world_edits.value = text
        self.note.content = f"Added *{html.escape(words)}*: press **Run** to fly the edited world."

    @staticmethod
    def _ref(world, index: int) -> str:
        """How the edits name a landmark: its noun phrase, or its index where several share the name."""
        name = world.landmarks[index].noun_phrase
        return name if sum(lm.noun_phrase == name for lm in world.landmarks) == 1 else str(index)
