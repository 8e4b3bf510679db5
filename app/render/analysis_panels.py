"""What the Analysis tab draws (pure functions, `app.page.analysis_view` shows them): an evaluation's success per slice
as bars, landmark x side as a heat map, a confusion matrix, and the versus table of two evaluations. Every bar, cell
and row is a button: a click types what it counts (`pick`) into the hidden field PICK_FIELD, and the tab lists the
episodes behind it (`app.jobs.analysis.Analyses.episodes`)."""

from __future__ import annotations

import html
import json
from collections.abc import Mapping
from typing import Any

from app.render.panels import hide_field_html, typing_script
from gsmn.analysis.slices import ATTRIBUTES, CONFUSIONS, NOT_READ

PICK_FIELD = "gsmn-pick"
PICK_CLICK = typing_script(PICK_FIELD, "this.dataset.pick")
HIDE_PICK_FIELD = hide_field_html(PICK_FIELD)
STYLE = "font-size:12px;line-height:1.35"
MATRICES = {f"{what} ({kind})": (name, kind == "ambiguous") for name, what in (
    ("grounded", "named -> grounded"), ("stopped_at", "named -> stopped at"), ("side", "side asked -> side reached"))
    for kind in ("unambiguous", "ambiguous")}


def pick(criteria: Mapping[str, str] | None = None, cell: tuple[str, str, str] | None = None,
         ambiguous: bool | None = None, title: str = "", versus: int | None = None) -> str:
    """What a click asks for, as the hidden field carries it (JSON); `versus`: a number of the versus table, which
    counts only the environments both evaluations flew."""
    return json.dumps({"where": dict(criteria or {}), "cell": list(cell) if cell else None, "ambiguous": ambiguous,
                       "title": title, "versus": versus})


def parse_pick(value: str) -> dict | None:
    """A click typed into PICK_FIELD ('{...}#1712345678'), None for anything else."""
    try:
        found = json.loads(value.rsplit("#", 1)[0])
    except ValueError:
        return None
    if not isinstance(found, dict) or not isinstance(found.get("where"), dict):
        return None
    cell = found.get("cell")
    return {"where": {str(k): str(v) for k, v in found["where"].items()},
            "cell": tuple(str(x) for x in cell) if isinstance(cell, list) and len(cell) == 3 else None,
            "ambiguous": found.get("ambiguous") if isinstance(found.get("ambiguous"), bool) else None,
            "title": str(found.get("title", "")),
            "versus": found["versus"] if isinstance(found.get("versus"), int) and not isinstance(found["versus"], bool)
            else None}


def _button(inner: str, picked: str, tip: str, style: str = "") -> str:
    return (f'<div role="button" data-pick="{html.escape(picked)}" title="{html.escape(tip)}" onclick="{PICK_CLICK}" '
            f'style="cursor:pointer;{style}">{inner}</div>')


def _colour(rate: float | None) -> str:
    """Red (0 %) to green (100 %) through amber, as the failure rows are coloured."""
    if rate is None:
        return "#ccc"
    r = 220 if rate < 50 else int(220 - (rate - 50) * 3.4)
    g = int(60 + rate * 1.4) if rate < 50 else 170
    return f"rgb({r},{g},70)"


def headline_html(analysis: Mapping[str, Any]) -> str:
    e = analysis["evaluation"]
    n, won = analysis["n"], analysis["successes"]
    lines = [f"<b>Evaluation {e['id']}</b>: {html.escape(e['label'])} &middot; {n} episodes, {won} successes "
             f"({100.0 * won / max(1, n):.1f} %). Bars: success with its 95 % interval; click any bar, cell or row "
             "for its episodes."]
    read = analysis["readings"]
    found = max(read["grounded"], read["goal_at"])
    if found == 0:
        lines.append("No map readings (grounded landmark, goal peak): this evaluation kept no maps, or its model has "
                     "no trained head to read them with.")
    elif found < n:
        lines.append(f"Map readings for {found} of {n} episodes (the others kept no maps).")
    lines += [f"&#9888; {html.escape(w)}" for w in analysis.get("warnings", [])]
    return f'<div style="{STYLE}">' + "<br>".join(lines) + "</div>"


def slices_html(analysis: Mapping[str, Any], attribute: str) -> str:
    """One attribute's values as bars, worst first."""
    rows = []
    for value, s in analysis["slices"][attribute].items():
        lo, hi = s["interval"]
        rate = s["rate"]
        bar = (f'<div style="position:relative;height:14px;background:#eee;border-radius:2px">'
               f'<div style="position:absolute;left:0;top:0;bottom:0;width:{rate or 0:.1f}%;'
               f'background:{_colour(rate)}"></div><div style="position:absolute;left:{lo:.1f}%;'
               f'width:{max(0.5, hi - lo):.1f}%;top:6px;height:2px;background:#333"></div></div>')
        label = (f'<div style="display:flex;justify-content:space-between"><span>{html.escape(value)}</span>'
                 f'<span>{s["successes"]}/{s["n"]} &middot; {rate:.0f} % [{lo:.0f}, {hi:.0f}]</span></div>')
        tip = f"{ATTRIBUTES[attribute]}: {value} - {s['n']} episodes, click for them"
        rows.append(_button(label + bar, pick({attribute: value}, title=f"{ATTRIBUTES[attribute]}: {value}"), tip,
                            "margin:3px 0"))
    if not rows or set(analysis["slices"][attribute]) == {NOT_READ}:
        return (f'<div style="{STYLE};opacity:.7">{html.escape(ATTRIBUTES[attribute])}: not read (no recorded '
                'maps)</div>')
    return f'<div style="{STYLE}">' + "".join(rows) + "</div>"


def crossed_html(analysis: Mapping[str, Any]) -> str:
    """Landmark x side: success per cell (colour) and episodes (number)."""
    grid = analysis["crossed"]["landmark x side"]
    sides = ("left", "right", "front", "back")
    head = "".join(f"<th style='font-weight:normal'>{s}</th>" for s in sides)
    body = []
    worst = sorted(grid, key=lambda k: sum(c["successes"] for c in grid[k].values())
                   / sum(c["n"] for c in grid[k].values()))
    for landmark in worst:
        cells = []
        for side in sides:
            c = grid[landmark].get(side)
            if c is None:
                cells.append("<td></td>")
                continue
            inner = _button(f"{c['successes']}/{c['n']}", pick({"landmark": landmark, "side": side},
                                                               title=f"{landmark}, {side} side"),
                            f"{landmark}, {side}: {c['rate']:.0f} % of {c['n']}",
                            f"background:{_colour(c['rate'])};color:#fff;text-align:center;padding:1px 3px")
            cells.append(f"<td>{inner}</td>")
        body.append(f"<tr><td>{html.escape(landmark)}</td>{''.join(cells)}</tr>")
    return (f'<table style="{STYLE};border-collapse:separate;border-spacing:2px"><tr><th></th>{head}</tr>'
            + "".join(body) + "</table>")


def confusion_html(analysis: Mapping[str, Any], matrix: str, ambiguous: bool) -> str:
    """A confusion matrix: a row per landmark (or side) asked, a column per reading, counts in cells; the diagonal
    (read as asked) green, the rest red by how many."""
    m = analysis["confusion_ambiguous" if ambiguous else "confusion"][matrix]
    if not m:
        return f'<div style="{STYLE};opacity:.7">No episode has this reading ({CONFUSIONS[matrix]}).</div>'
    reads = sorted({r for row in m.values() for r in row}, key=lambda r: (r not in m, r))
    head = "".join(f"<th style='font-weight:normal;writing-mode:vertical-rl;transform:rotate(180deg)'>"
                   f"{html.escape(r)}</th>" for r in reads)
    body = []
    for asked, row in m.items():
        cells = []
        for read in reads:
            count = row.get(read, 0)
            if not count:
                cells.append("<td></td>")
                continue
            colour = "#3a9d5d" if read == asked else f"rgba(200,50,40,{min(1.0, 0.35 + 0.15 * count):.2f})"
            cells.append("<td>" + _button(str(count), pick(cell=(matrix, asked, read), ambiguous=ambiguous,
                                                          title=f"asked {asked}, read {read}"),
                                          f"asked {asked}, read {read}: {count} episodes",
                                          f"background:{colour};color:#fff;text-align:center;padding:1px 4px")
                         + "</td>")
        body.append(f"<tr><td style='white-space:nowrap'>{html.escape(asked)}</td>{''.join(cells)}</tr>")
    return (f'<div style="{STYLE}">{html.escape(CONFUSIONS[matrix])}; rows: asked, columns: read</div>'
            f'<div style="overflow-x:auto"><table style="{STYLE};border-collapse:separate;border-spacing:2px">'
            f"<tr><th></th>{head}</tr>" + "".join(body) + "</table></div>")


def versus_html(analysis: Mapping[str, Any]) -> str:
    """The two evaluations' rates and the paired differences, the largest slices first."""
    if "versus" not in analysis:
        return ""
    v, e, o = analysis["versus_summary"], analysis["evaluation"], analysis["versus_evaluation"]
    overall = v["overall"]
    lines = [f"<b>Evaluation {e['id']}</b> ({html.escape(e['label'])}) against <b>evaluation {o['id']}</b> "
             f"({html.escape(o['label'])}) on the {v['n']} environments both flew: {overall['rate']:.1f} % against "
             f"{overall['rate_versus']:.1f} %; <b>{overall['fixed']}</b> fixed (only {e['id']} succeeded), "
             f"<b>{overall['broken']}</b> broken (only {o['id']} succeeded), sign test p = {overall['p']:.3g}."]
    rows = []
    for s in v["largest"]:
        where = ", ".join(f"{ATTRIBUTES[a]}: {x}" for a, x in s["slice"].items())
        marker = "&#9679; " if s["p_adjusted"] < 0.05 else ""
        inner = (f"{marker}{html.escape(where)} &middot; {s['n']} episodes &middot; {s['rate']:.0f} % vs "
                 f"{s['rate_versus']:.0f} % &middot; fixed {s['fixed']}, broken {s['broken']}, p {s['p']:.2g} "
                 f"(corrected {s['p_adjusted']:.2g})")
        rows.append(_button(inner, pick(s["slice"], title=where, versus=o["id"]),
                            "click for these episodes (as the first evaluation flew them)",
                            "padding:2px 0;border-bottom:1px solid #eee"))
    if not rows:
        rows.append("No slice of five or more paired episodes differs.")
    return (f'<div style="{STYLE}">' + "<br>".join(lines) + "<div style='margin-top:4px'>Slices that differ most, up "
            f"to two attributes combined (&#9679;: p &lt; 0.05 after Holm's correction for the {v['tested']} slices "
            "tested, which some would pass by chance alone):</div>" + "".join(rows) + "</div>")
