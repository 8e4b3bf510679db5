"""The page's "Analysis" tab (viser; the tab's jobs UI thread, `app.page.jobs_view`): an evaluation across all its
episodes (`app.jobs.analysis`): success per slice, landmark x side, the confusion matrices, and against another
evaluation of the same environments slice by slice. A click on any bar, cell or row lists its episodes; a click on
an episode flies it again in the live view and moves the timeline to the step it went wrong. The shipped
evaluations are offered beside the record's and imported the first time they are picked. What the tab draws is
`app.render.analysis_panels`' (pure functions).
"""

from __future__ import annotations

import html
import math

import viser

from app.jobs.db import FINISHED, EpisodeRow
from app.live.commands import RunnerError
from app.page.failures_view import show_page
from app.render.analysis_panels import (
    HIDE_PICK_FIELD,
    MATRICES,
    PICK_FIELD,
    confusion_html,
    crossed_html,
    headline_html,
    parse_pick,
    slices_html,
    versus_html,
)
from app.render.jobs_panels import evaluation_label, note_html
from app.render.panels import error_html
from gsmn.analysis.slices import ATTRIBUTES

ROWS = 10  # episode buttons per page
NOTHING = "(nothing)"
SHIPPED = "shipped: "
BY_TITLE = {title: name for name, title in ATTRIBUTES.items()}


class AnalysisTab:
    """The Analysis tab's part of `app.page.jobs_view.JobsView` (its controls are attributes of the view)."""

    def _build_analysis(self, gui, panel) -> None:
        self.analysis: dict | None = None
        self.analysis_rows: list[EpisodeRow] = []
        self.analysis_page = 0
        self._analysable: dict[str, tuple[str, int | str]] = {}
        with panel.add_tab("Analysis", viser.Icon.CHART_BAR):
            gui.add_html(HIDE_PICK_FIELD)
            self.pick_field = gui.add_text(PICK_FIELD, "")  # hidden: a click on the analysis types into it
            with gui.add_folder("Analyse an evaluation"):
                self.an_evaluation = gui.add_dropdown("Evaluation", ("(none yet)",),
                                                      hint="a finished evaluation of the record, or one shipped "
                                                           "with the checkpoints (Table 1's and Table 2's)")
                self.an_versus = gui.add_dropdown("Against", (NOTHING,), hint="another evaluation of the same "
                                                  "environments: what the first fixed and broke, slice by slice")
                self.an_button = gui.add_button("Analyse", icon=viser.Icon.CHART_BAR)
                self.an_status = gui.add_markdown("Pick an evaluation and press Analyse.")
            self.an_headline = gui.add_html("")
            with gui.add_folder("Success by slice"):
                self.an_attribute = gui.add_dropdown("Slice by", tuple(ATTRIBUTES.values()))
                self.an_slices = gui.add_html("")
            with gui.add_folder("Landmark x side", expand_by_default=False):
                self.an_crossed = gui.add_html("")
            with gui.add_folder("Against the other"):
                self.an_versus_html = gui.add_html(note_html("Pick an evaluation to compare against."))
            with gui.add_folder("What the model read"):  # just above the episodes a click on its cells lists
                self.an_matrix = gui.add_dropdown("Matrix", tuple(MATRICES))
                self.an_confusion = gui.add_html("")
            with gui.add_folder("Episodes"):
                self.an_note = gui.add_markdown("Click a bar, a cell or a row above: its episodes are listed here.")
                self.an_rows = [gui.add_button(f"analysed {k}", visible=False) for k in range(ROWS)]
                self.an_pager = gui.add_button_group("Episodes page", ("Previous", "Next"))
                self.an_detail = gui.add_html("")

    # -- what can be analysed ------------------------------------------------------------------------------------
    def _refresh_analysable(self, evaluations) -> None:
        """The record's finished evaluations (newest first) and the shipped ones not yet imported."""
        choices: dict[str, tuple[str, int | str]] = {}
        for e in reversed(evaluations):
            if e.status == FINISHED:
                choices[evaluation_label(e)] = ("evaluation", e.id)
        for s in self.jobs.analyses.shipped(evaluations):
            if s["evaluation_id"] is None:
                choices[SHIPPED + s["label"]] = ("shipped", s["key"])
        self._analysable = choices
        for dropdown, extra in ((self.an_evaluation, ()), (self.an_versus, (NOTHING,))):
            options = (*extra, *choices) or ("(none yet)",)
            if tuple(dropdown.options) != options:
                value = dropdown.value
                dropdown.options = options
                if value in options:
                    dropdown.value = value

    def _evaluation_of(self, choice: str) -> int | None:
        kind, ref = self._analysable.get(choice, (None, None))
        if kind == "shipped":
            self.an_status.content = f"Importing the shipped evaluation {html.escape(choice[len(SHIPPED):])}..."
            return self.jobs.analyses.import_shipped(str(ref)).id
        return ref if kind == "evaluation" else None

    # -- analysing ----------------------------------------------------------------------------------------------
    def _analyse(self) -> None:
        try:
            first = self._evaluation_of(self.an_evaluation.value)
            if first is None:
                self.an_status.content = "No finished evaluation yet: evaluate a checkpoint in the Failures tab."
                return
            other = self._evaluation_of(self.an_versus.value) if self.an_versus.value != NOTHING else None
            self.analysis = self.jobs.analyses.analysis(first, other)
        except RunnerError as err:
            self.an_status.content = error_html(f"**Not analysed:** {html.escape(str(err))}")
            return
        self.an_status.content = f"Evaluation {first}" + (f" against evaluation {other}." if other else ".")
        self.analysis_rows, self.analysis_page = [], 0
        self._show_analysis()
        self._show_analysis_rows("")
        self._refresh()  # an imported shipped evaluation is now one of the record's: the menus name it so
        for dropdown, chosen in ((self.an_evaluation, first), (self.an_versus, other)):
            label = next((k for k, v in self._analysable.items() if v == ("evaluation", chosen)), NOTHING)
            if label in dropdown.options:
                dropdown.value = label

    def _show_analysis(self) -> None:
        a = self.analysis
        if a is None:
            return
        self.an_headline.content = headline_html(a)
        self.an_slices.content = slices_html(a, BY_TITLE.get(self.an_attribute.value, "landmark"))
        self.an_crossed.content = crossed_html(a)
        self.an_confusion.content = confusion_html(a, *MATRICES[self.an_matrix.value])
        self.an_versus_html.content = versus_html(a) or note_html("Pick an evaluation to compare against.")

    def _picked(self, value: str) -> None:
        found = parse_pick(value)
        if found is None or self.analysis is None:
            return
        try:
            self.analysis_rows = self.jobs.analyses.episodes(self.analysis["evaluation"]["id"], found["where"],
                                                             found["cell"], found["ambiguous"], found["versus"])
        except RunnerError as err:
            self.an_note.content = error_html(html.escape(str(err)))
            return
        self.analysis_page = 0
        self._show_analysis_rows(found["title"])

    def _show_analysis_rows(self, title: str | None = None) -> None:
        if title is not None:
            self.analysis_title = title
        n = len(self.analysis_rows)
        self.analysis_page, pages = show_page(self.an_rows, self.analysis_rows, self.analysis_page)
        what = f"**{html.escape(self.analysis_title)}**: " if getattr(self, "analysis_title", "") else ""
        self.an_note.content = (f"{what}{n} episode{'s' if n != 1 else ''}; page {self.analysis_page + 1} of "
                                f"{pages}. Click one to fly it again in the live view (shown at the step it went "
                                "wrong, where that is known)."
                                if n else "Click a bar, a cell or a row above: its episodes are listed here.")

    def _page_analysis(self, button: str) -> None:
        pages = max(1, math.ceil(len(self.analysis_rows) / ROWS))
        self.analysis_page = max(0, min(pages - 1, self.analysis_page + (1 if button == "Next" else -1)))
        self._show_analysis_rows()

    def _replay_analysed(self, k: int) -> None:
        if self.analysis_page * ROWS + k >= len(self.analysis_rows):
            return
        row = self.analysis_rows[self.analysis_page * ROWS + k]
        step = self.jobs.db.facts(row.evaluation_id).get(row.env_id, {}).get("went_wrong")
        self._replay(row, self.an_detail, step)
