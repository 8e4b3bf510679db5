"""The page's words for researchers, each with a plain gloss: all of them in the page's "What the words mean" folder,
and, where a panel uses one of the terms of art, a tooltip on it (`glossed`: a dotted underline, the gloss on hover).
Presenter mode speaks plainly already and uses none of them.
"""

from __future__ import annotations

import html
import re

GLOSSARY: dict[str, str] = {
    "P(stop)": "how sure the model is that it has arrived: it says STOP when this passes 0.5",
    "P(named)": "how likely a map cell holds the landmark the instruction names (the relevance map, read)",
    "P(goal)": "how likely a map cell is where the instruction asks the drone to stop (the goal map, read)",
    "relevance AUC": "how well the relevance map tells the named landmark's cells from the rest: 1 perfect, "
                     "0.5 chance",
    "goal mass": "the share of the goal map's probability inside the success region: 1 all of it, near 0 none",
    "J_percept": "the training signal that teaches the model to name the landmark in each map cell",
    "J_ground": "the training signal that teaches the model which map cells hold the landmark the instruction names",
    "J_plan": "the training signal that teaches the model where the goal is on the map",
    "J_lang": "the training signal that teaches the model to read the landmark and side from the instruction",
    "N_D": "rollouts flown per fine-tuning iteration, each adding its steps to the training data",
    "beta0": "how often the expert flies instead of the model early in fine-tuning (beta0 to the power i in "
             "iteration i)",
    "success region": "the circle around the landmark, on the side asked, where saying STOP counts as success",
}
PLAIN = {"success region"}  # in the list, but plain enough in a sentence to need no tooltip there
_TERMS = re.compile("|".join(re.escape(term) for term in sorted(set(GLOSSARY) - PLAIN, key=len, reverse=True)))


def glossed(text: str) -> str:
    """`text` (Markdown or HTML written by the page, not typed by a user) with each glossary word wrapped in a span
    whose tooltip is its gloss. One pass: a gloss is never glossed again."""
    return _TERMS.sub(lambda m: f'<span title="{html.escape(GLOSSARY[m.group(0)], quote=True)}" '
                                f'style="text-decoration:underline dotted;cursor:help">{m.group(0)}</span>', text)


def glossary_markdown() -> str:
    """Every word with its gloss, one line each."""
    return "  \n".join(f"**{html.escape(term)}**: {html.escape(gloss)}." for term, gloss in GLOSSARY.items())
