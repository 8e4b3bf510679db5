"""Failures across a whole evaluation: success per slice, what the model read instead of what was asked, and two
evaluations of the same environments compared slice by slice (`gsmn analyze slices`, the Failures tab's analysis).

    gsmn analyze slices EVAL.json [--record REC] [--versus OTHER.json] [--json OUT] [--markdown]

Each evaluated episode gets its *facts* (`episode_facts`): what its world and its end say about it, and three
readings of the model's maps at the end of the episode (from its attribution, gsmn.attribution):

    landmarks     how many landmarks its world holds
    distance      start to goal in a straight line (m)
    demonstration the demonstration path's length (m; gsmn.task.demo)
    stopped_at    the landmark the drone ended at (stopped or not): the named landmark whenever it ended in its region
                  (closer than the success radius), else the nearest whose region holds it, "no landmark" when none;
                  the side of it (stopped_side, as the metric reads sides: gsmn.task.metrics) and which it is
                  (stopped_which: the named one, another of the same name, another landmark, none)
    reached_side  the side of the named landmark the drone ended on
    grounded      the landmark the relevance map singles out: the one of the world whose cell has the highest
                  P(named) (the grounding head's reading); None where the model has no trained grounding head
    goal_at       the landmark whose region holds the goal map's peak, read as stopped_at is, and the side of it
                  (goal_side, goal_which); None where the model has no trained goal head
    went_wrong    the step from which the attributed stage's map stayed below its agreement with the ground truth
                  (gsmn.analysis.truth), None where not known

Facts are computed once, when an evaluation runs (kept beside each episode's attributed stage: the compact Table 2
evaluations, the dashboard's record), and for an evaluation that lacks them from its world (built from the
environment id) and, where given, its recorded maps; a world costs ~10 ms to build, so they are kept, not redone.

`attribute_values` turns an episode into the value it has for each attribute in ATTRIBUTES; `analyze` counts them:
slices (episodes, successes, rate with a 95 % Wilson interval, worst first), confusion matrices (named landmark to
grounded landmark and to the landmark stopped at, asked side to reached side; the ambiguous instructions counted
apart), and with a second evaluation of the same environments the paired difference per slice (fixed and broken
episodes, two-sided exact sign test) with the largest significant differences over up to two attributes combined.
`select` gives the episodes behind any number: every bar, row and cell of the page opens its episodes with it.
"""

from __future__ import annotations

import itertools
import math
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from gsmn.task.metrics import side_of, sign_test, wilson

NO_LANDMARK = "no landmark"
NOT_READ = "not read"  # a reading the evaluation has no maps (or no trained head) for
SUCCESS = "success"

# attribute -> what it is, as the page and the markdown name it. The first group depends only on the environment
# (the same in two evaluations of the same environments: the `versus` table slices on these); the rest on the flight.
ATTRIBUTES: dict[str, str] = {
    "landmark": "landmark named",
    "side": "side asked",
    "ambiguous": "instruction",
    "landmarks": "landmarks in the world",
    "distance": "start to goal",
    "demonstration": "demonstration length",
    "stage": "attributed stage",
    "went_wrong": "went wrong at step",
    "outcome": "outcome",
    "grounding": "relevance map singled out",
    "goal": "goal map's peak",
    "stopped": "ended at",
}
ENVIRONMENT = ("landmark", "side", "ambiguous", "landmarks", "distance", "demonstration")
FACTS_VERSION = 2  # facts of another version are computed again (2: the landmark ended at is the named one first)
WHICH = ("named", "same name", "other", "none")
CONFUSIONS = {"grounded": "named landmark -> landmark the relevance map singles out",
              "stopped_at": "named landmark -> landmark the drone ended at",
              "side": "side asked -> side of the named landmark the drone ended on"}
DISTANCE_BINS = (10.0, 20.0, 30.0)  # m: "under 10 m", "10-20 m", "20-30 m", "30 m or more"
DEMONSTRATION_BINS = (15.0, 25.0, 35.0)
STEP_BINS = (20, 40, 60)
MIN_SLICE = 5  # the versus table's combined slices: at least this many paired episodes


# -- per episode ----------------------------------------------------------------------------------------------------
def _place(world, xy: tuple[float, float], radius: float, named_index: int) -> tuple[str, str | None, str]:
    """Which landmark's region (closer than `radius` to its centre) holds xy: the named landmark's whenever it does,
    else the nearest one's; its noun phrase, the side of it xy lies on (as the metric reads sides), and which it is
    (WHICH: the named landmark, another of the same name, another landmark, or none)."""
    named = world.landmarks[named_index]
    start = (world.start_x, world.start_y)
    if math.dist(xy, (named.x, named.y)) < radius:
        return named.noun_phrase, side_of((named.x, named.y), start, xy), "named"
    distance, i = min((math.dist(xy, (lm.x, lm.y)), i) for i, lm in enumerate(world.landmarks))
    if distance >= radius:
        return NO_LANDMARK, None, "none"
    lm = world.landmarks[i]
    return lm.noun_phrase, side_of((lm.x, lm.y), start, xy), "same name" if lm.noun_phrase == named.noun_phrase \
        else "other"


def episode_facts(episode: Mapping[str, Any], world, attribution: Mapping[str, Any] | None,
                  success_radius: float = 6.0, demonstration: float | None = None) -> dict[str, Any]:
    """The facts of one evaluated episode (see the module docstring): `episode` as `gsmn eval --json` writes it,
    `world` its WorldSpec, `attribution` its `Attribution.to_dict()` (None: no recorded maps), `demonstration` the
    length of its demonstration path in m (None: computed here)."""
    named = world.landmarks[int(episode["landmark_index"])]
    start = (world.start_x, world.start_y)
    final = (float(episode["final_x"]), float(episode["final_y"]))
    stopped_at, stopped_side, stopped_which = _place(world, final, success_radius, int(episode["landmark_index"]))
    if demonstration is None:
        demonstration = demonstration_length(world, (float(episode["goal_x"]), float(episode["goal_y"])))
    facts: dict[str, Any] = {
        "version": FACTS_VERSION, "landmarks": len(world.landmarks),
        "distance": round(math.dist(start, (float(episode["goal_x"]), float(episode["goal_y"]))), 2),
        "demonstration": None if demonstration is None else round(demonstration, 2),
        "stopped_at": stopped_at, "stopped_side": stopped_side, "stopped_which": stopped_which,
        "reached_side": side_of((named.x, named.y), start, final),
        "grounded": None, "goal_at": None, "goal_side": None, "goal_which": None, "went_wrong": None}
    if attribution:
        facts.update(map_readings(attribution, world, int(episode["landmark_index"]), success_radius))
    return facts


def map_readings(attribution: Mapping[str, Any], world, named_index: int, success_radius: float = 6.0
                 ) -> dict[str, Any]:
    """`grounded`, `goal_at`, `goal_side`, `goal_which` and `went_wrong` from an episode's attribution (its
    `to_dict()`); `named_index` the landmark the instruction names. The grounding head's reading puts the named
    landmark against the landmarks of other names only (gsmn.attribution), so `grounded` is its name or another."""
    named = world.landmarks[named_index].noun_phrase
    out: dict[str, Any] = {"grounded": None, "goal_at": None, "goal_side": None, "goal_which": None,
                           "went_wrong": went_wrong(attribution)}
    if attribution.get("grounded") is not None:  # a trained grounding head: the highest P(named) of the landmarks
        other, p_other = attribution.get("other_landmark"), attribution.get("p_named_other")
        beaten = other is not None and p_other is not None and p_other > attribution["p_named"]
        out["grounded"] = other if beaten else named
    if attribution.get("goal_right") is not None:  # a trained goal head
        out["goal_at"], out["goal_side"], out["goal_which"] = _place(
            world, (float(attribution["goal_peak_x"]), float(attribution["goal_peak_y"])), success_radius, named_index)
    return out


def valid_facts(facts: Any) -> bool:
    """Whether kept facts are of this version and of the types read here (damaged or older ones are computed again)."""
    if not isinstance(facts, dict) or facts.get("version") != FACTS_VERSION:
        return False
    numbers = ("distance", "demonstration")
    names = ("stopped_at", "stopped_side", "stopped_which", "reached_side", "grounded", "goal_at", "goal_side",
             "goal_which")
    return (isinstance(facts.get("landmarks"), int) and isinstance(facts.get("stopped_at"), str)
            and all(facts.get(k) is None or isinstance(facts[k], (int, float)) for k in numbers)
            and all(facts.get(k) is None or isinstance(facts[k], str) for k in names)
            and (facts.get("went_wrong") is None or isinstance(facts["went_wrong"], int)))


def went_wrong(attribution: Mapping[str, Any]) -> int | None:
    """The step from which the attributed stage's map stayed wrong (a merged stage: its first part that has one)."""
    failed_from, stage = attribution.get("failed_from") or {}, attribution.get("stage")
    if not stage:
        return None
    for part in stage.split("_or_"):
        if failed_from.get(part) is not None:
            return int(failed_from[part])
    return None


def demonstration_length(world, goal_xy: tuple[float, float]) -> float | None:
    """The demonstration path's length (m) from the start to the goal; None where no path is acceptable."""
    from gsmn.task.demo import DemoPathError, demonstration_path, path_length

    try:
        return float(path_length(demonstration_path(world, goal_xy)))
    except DemoPathError:
        return None


# -- the value of each attribute --------------------------------------------------------------------------------------
def _binned(x: float | None, bins: Sequence[float], unit: str) -> str:
    if x is None:
        return NOT_READ
    if x < bins[0]:
        return f"under {bins[0]:g} {unit}"
    for lo, hi in itertools.pairwise(bins):
        if x < hi:
            return f"{lo:g}-{hi:g} {unit}"
    return f"{bins[-1]:g} {unit} or more"


def _against(read: str | None, side: str | None, which: str | None, named: str, asked: str) -> str:
    """A map reading or the place ended at, against what the instruction asked (`which`: WHICH, None for the
    grounded landmark, which is never another of the named landmark's name)."""
    if read is None:
        return NOT_READ
    if read == NO_LANDMARK:
        return "no landmark"
    if which == "same name":
        return "another landmark of the same name"
    if read != named or which == "other":
        return "another landmark"
    return "the named landmark" if side is None else (
        "the named landmark, side asked" if side == asked else "the named landmark, another side")


def outcome(row: Mapping[str, Any]) -> str:
    if row["success"]:
        return SUCCESS
    if not row["stopped"]:
        return "never stopped"
    return "stopped at the landmark, wrong side" if row.get("landmark_success") else "stopped elsewhere"


def attribute_values(row: Mapping[str, Any]) -> dict[str, str]:
    """The value each of ATTRIBUTES has for an episode `row` (`normalise`d); readings a row lacks are NOT_READ."""
    facts = row.get("facts") or {}
    named, asked = row["landmark"], row["side"]
    landmarks = facts.get("landmarks")
    step = facts.get("went_wrong")
    return {
        "landmark": named, "side": asked, "ambiguous": "ambiguous" if row["ambiguous"] else "unambiguous",
        "landmarks": NOT_READ if landmarks is None else str(landmarks),
        "distance": _binned(facts.get("distance"), DISTANCE_BINS, "m"),
        "demonstration": _binned(facts.get("demonstration"), DEMONSTRATION_BINS, "m"),
        "stage": SUCCESS if row["success"] else (row.get("stage") or NOT_READ),
        "went_wrong": SUCCESS if row["success"] else _binned(step, STEP_BINS, "steps").replace(" steps", ""),
        "outcome": outcome(row),
        "grounding": _against(facts.get("grounded"), None, None, named, asked),
        "goal": _against(facts.get("goal_at"), facts.get("goal_side"), facts.get("goal_which"), named, asked),
        "stopped": _against(facts["stopped_at"], facts.get("stopped_side"), facts.get("stopped_which"), named, asked)
        if "stopped_at" in facts else NOT_READ}


def normalise(episode: Mapping[str, Any]) -> dict[str, Any]:
    """An episode of a `gsmn eval --json` file, a compact evaluation or the dashboard's record, as the rows here
    read it: env_id, landmark, side, ambiguous, success, landmark_success, stopped, steps, stage, facts."""
    return {"env_id": int(episode["env_id"]), "landmark": episode.get("noun_phrase", episode.get("landmark")),
            "side": episode["side"], "ambiguous": bool(episode["ambiguous"]), "success": bool(episode["success"]),
            "landmark_success": bool(episode.get("landmark_success", False)), "stopped": bool(episode["stopped"]),
            "steps": int(episode.get("steps", 0)), "stage": episode.get("stage"), "facts": episode.get("facts")}


# -- counting -------------------------------------------------------------------------------------------------------
def rate_of(successes: int, n: int) -> dict[str, Any]:
    lo, hi = wilson(successes, n)
    return {"n": n, "successes": successes, "rate": round(100.0 * successes / n, 2) if n else None,
            "interval": [round(100.0 * lo, 2), round(100.0 * hi, 2)]}


def _worst_first(stats: dict[str, dict]) -> dict[str, dict]:
    return dict(sorted(stats.items(), key=lambda kv: (kv[1]["successes"] / kv[1]["n"], -kv[1]["n"], kv[0])))


def slices(rows: Sequence[Mapping[str, Any]], values: Sequence[dict[str, str]] | None = None) -> dict[str, dict]:
    """Per attribute, per value: episodes, successes, rate (%) and its 95 % interval (%), worst first."""
    values = values if values is not None else [attribute_values(r) for r in rows]
    out: dict[str, dict] = {}
    for attribute in ATTRIBUTES:
        n: Counter = Counter()
        won: Counter = Counter()
        for row, v in zip(rows, values, strict=True):
            n[v[attribute]] += 1
            won[v[attribute]] += bool(row["success"])
        out[attribute] = _worst_first({value: rate_of(won[value], n[value]) for value in n})
    return out


def crossed(rows: Sequence[Mapping[str, Any]], first: str, second: str,
            values: Sequence[dict[str, str]] | None = None) -> dict[str, dict[str, dict]]:
    """Two attributes crossed (landmark x side as a heat map): {value of first: {value of second: rate_of}}."""
    values = values if values is not None else [attribute_values(r) for r in rows]
    n: Counter = Counter()
    won: Counter = Counter()
    for row, v in zip(rows, values, strict=True):
        n[v[first], v[second]] += 1
        won[v[first], v[second]] += bool(row["success"])
    out: dict[str, dict[str, dict]] = {}
    for (a, b) in sorted(n):
        out.setdefault(a, {})[b] = rate_of(won[a, b], n[a, b])
    return out


def read_of(row: Mapping[str, Any], matrix: str) -> tuple[str, str | None]:
    """What a confusion matrix counts for an episode: (asked, read), read None where the episode has no reading.
    The landmark ended at, when another of the named landmark's name, reads "another NAME"."""
    facts = row.get("facts") or {}
    if matrix == "side":
        return row["side"], facts.get("reached_side")
    read = facts.get(matrix)
    if matrix == "stopped_at" and read is not None and facts.get("stopped_which") == "same name":
        read = f"another {read}"
    return row["landmark"], read


def confusion(rows: Iterable[Mapping[str, Any]]) -> dict[str, dict[str, dict[str, int]]]:
    """{"grounded" | "stopped_at" | "side": {named or asked: {read: count}}} over the rows given (episodes without
    the reading are left out of that matrix)."""
    out: dict[str, dict[str, Counter]] = {name: {} for name in CONFUSIONS}
    for row in rows:
        for name in CONFUSIONS:
            asked, read = read_of(row, name)
            if read is not None:
                out[name].setdefault(asked, Counter())[read] += 1
    return {name: {asked: dict(reads.most_common()) for asked, reads in sorted(m.items())}
            for name, m in out.items()}


def select(rows: Sequence[Mapping[str, Any]], criteria: Mapping[str, str] | None = None,
           cell: tuple[str, str, str] | None = None, ambiguous: bool | None = None) -> list[int]:
    """The env ids of the episodes behind a number: those whose attributes have the given values (`criteria`,
    attribute -> value), and/or those counted in a confusion cell (`cell`: matrix, named or asked, read) with
    `ambiguous` saying which instructions the matrix counted (None: all)."""
    out = []
    for row in rows:
        if ambiguous is not None and bool(row["ambiguous"]) != ambiguous:
            continue
        if criteria:
            v = attribute_values(row)
            if any(v.get(a) != value for a, value in criteria.items()):
                continue
        if cell is not None and read_of(row, cell[0]) != (cell[1], cell[2]):
            continue
        out.append(int(row["env_id"]))
    return out


# -- two evaluations ------------------------------------------------------------------------------------------------
def paired(rows: Sequence[Mapping[str, Any]], other: Sequence[Mapping[str, Any]]) -> list[tuple[dict, dict]]:
    """The episodes of the same environments in both, in the first's order."""
    by_env = {int(r["env_id"]): r for r in other}
    return [(r, by_env[int(r["env_id"])]) for r in rows if int(r["env_id"]) in by_env]


def _difference(pairs: Sequence[tuple[Mapping, Mapping]]) -> dict[str, Any]:
    fixed = sum(1 for a, b in pairs if a["success"] and not b["success"])
    broken = sum(1 for a, b in pairs if b["success"] and not a["success"])
    n = len(pairs)
    return {"n": n, "rate": round(100.0 * sum(a["success"] for a, _ in pairs) / n, 2) if n else None,
            "rate_versus": round(100.0 * sum(b["success"] for _, b in pairs) / n, 2) if n else None,
            "fixed": fixed, "broken": broken, "p": sign_test(fixed, broken)}


def versus(rows: Sequence[Mapping[str, Any]], other: Sequence[Mapping[str, Any]], top: int = 12) -> dict[str, Any]:
    """The first evaluation against `other` on the environments both flew: per slice of ENVIRONMENT both rates and
    the paired difference ("fixed": episodes only the first won, "broken": only `other` won; p of a two-sided sign
    test), and `largest`: the slices over up to two attributes combined with the largest differences, those still
    significant (p < 0.05) after Holm's correction for the `tested` slices first."""
    pairs = paired(rows, other)
    values = [attribute_values(a) for a, _ in pairs]
    out: dict[str, Any] = {"n": len(pairs), "overall": _difference(pairs), "slices": {}}
    groups: dict[tuple, list] = {}
    for (a, b), v in zip(pairs, values, strict=True):
        for attribute in ENVIRONMENT:
            groups.setdefault(((attribute, v[attribute]),), []).append((a, b))
        for first, second in itertools.combinations(ENVIRONMENT, 2):
            groups.setdefault(((first, v[first]), (second, v[second])), []).append((a, b))
    for key, group in groups.items():
        if len(key) == 1:
            (attribute, value), = key
            out["slices"].setdefault(attribute, {})[value] = _difference(group)
    for attribute, found in out["slices"].items():
        out["slices"][attribute] = dict(sorted(found.items(), key=lambda kv: (kv[1]["p"], kv[0])))
    ranked = []
    for key, group in groups.items():
        d = _difference(group)
        if d["n"] >= MIN_SLICE and d["fixed"] + d["broken"]:
            ranked.append({"slice": dict(key), **d})
    for s, adjusted in zip(ranked, holm([s["p"] for s in ranked]), strict=True):
        s["p_adjusted"] = adjusted
    # the significant first, each group by its difference in success (points), the larger first
    ranked.sort(key=lambda s: (s["p_adjusted"] >= 0.05, -abs(s["rate"] - s["rate_versus"]), s["p"], len(s["slice"])))
    out["tested"] = len(ranked)
    out["largest"] = [s for s in ranked if s["fixed"] != s["broken"]][:top]
    return out


def holm(ps: Sequence[float]) -> list[float]:
    """Holm's step-down adjustment of p-values for testing them all at once (the versus table tests every slice of
    up to two attributes: some would pass p < 0.05 by chance alone)."""
    order = sorted(range(len(ps)), key=lambda i: ps[i])
    out = [1.0] * len(ps)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (len(ps) - rank) * ps[i]))
        out[i] = running
    return out


def analyze(rows: Sequence[Mapping[str, Any]], other: Sequence[Mapping[str, Any]] | None = None) -> dict[str, Any]:
    """Everything the analysis view and `gsmn analyze slices --json` show of an evaluation's `rows` (`normalise`d):
    {"n", "slices", "crossed": landmark x side, "confusion" (unambiguous instructions), "confusion_ambiguous",
    "readings" (how many episodes have each map reading), and with `other` "versus" (`versus`'s slices) and
    "versus_summary"}."""
    values = [attribute_values(r) for r in rows]
    out: dict[str, Any] = {
        "n": len(rows), "successes": sum(bool(r["success"]) for r in rows),
        "attributes": ATTRIBUTES, "slices": slices(rows, values),
        "crossed": {"landmark x side": crossed(rows, "landmark", "side", values)},
        "confusion": confusion(r for r in rows if not r["ambiguous"]),
        "confusion_ambiguous": confusion(r for r in rows if r["ambiguous"]),
        "readings": {key: sum(1 for r in rows if (r.get("facts") or {}).get(key) is not None)
                     for key in ("landmarks", "grounded", "goal_at", "stopped_at", "went_wrong")}}
    if other is not None:
        v = versus(rows, other)
        out["versus"] = v["slices"]
        out["versus_summary"] = {"n": v["n"], "overall": v["overall"], "largest": v["largest"], "tested": v["tested"]}
    return out


# -- an evaluation file -----------------------------------------------------------------------------------------------
def config_of(results: Mapping[str, Any]):
    """The RunConfig an evaluation flew under: its own ("config"), else its recipe's preset and look (compact Table 2
    evaluations; a recipe saved without a look flew MuJoCo's shadow passes), else the paper's."""
    from gsmn.config import RunConfig, preset, with_overrides

    if results.get("config"):
        return RunConfig.from_dict(results["config"])
    recipe = results.get("recipe") or {}
    return with_overrides(preset(recipe.get("preset", "paper")),
                          {"camera.shadow_method": recipe.get("shadow_method", "mujoco")})


def with_facts(results: Mapping[str, Any], record=None, checkpoint=None, log=None) -> list[dict[str, Any]]:
    """The rows of an evaluation file (`gsmn eval --json`, or a compact evaluation) with their facts: those it keeps,
    else computed from each episode's world and, given its `--record` folder, the recorded maps read by the
    checkpoint's heads (`checkpoint`, default: the one the evaluation names)."""
    from gsmn.world.spec import world_for_env

    if not isinstance(results, Mapping) or not isinstance(results.get("episodes"), list):
        raise ValueError("not an evaluation: no list of episodes (a `gsmn eval --json` file or a compact evaluation)")
    config = config_of(results)
    attribution_of = _attributions(results, record, checkpoint, config) if record is not None else None
    rows = []
    for episode in results["episodes"]:
        row = normalise(episode)
        unstaged = attribution_of is not None and row["stage"] is None and not row["success"]
        if not valid_facts(row["facts"]) or (attribution_of is not None and row["facts"].get("grounded") is None) \
                or unstaged:
            attribution = attribution_of(episode) if attribution_of is not None else None
            if not valid_facts(row["facts"]) or row["facts"].get("grounded") is None:
                world = world_for_env(row["env_id"], config.world)
                row["facts"] = episode_facts(episode, world, attribution, config.task.success_radius)
            if attribution is not None and row["stage"] is None and not row["success"]:
                row["stage"] = attribution["stage"]
        rows.append(row)
    if log is not None and attribution_of is not None:
        missing = sum(1 for r in rows if r["facts"].get("grounded") is None and r["facts"].get("goal_at") is None)
        if missing:
            log(f"{missing} of {len(rows)} episodes have no readable recording in {record}: no map readings for them")
    return rows


def _attributions(results, record, checkpoint, config):
    from pathlib import Path

    from gsmn.attribution import Heads, attribute_record, load_trace, trace_path
    from gsmn.evaluation import checkpoint_path
    from gsmn.model.checkpoint import load_checkpoint

    model, *_ = load_checkpoint(checkpoint or checkpoint_path("gsmn", results.get("checkpoint")))
    heads = Heads.of(model) if getattr(model.heads, "goal", None) is not None else None

    def attribution_of(episode) -> dict | None:
        path = trace_path(Path(record), int(episode["env_id"]))
        if heads is None or not path.is_file():
            return None
        return attribute_record(episode, load_trace(path), heads, config).to_dict()

    return attribution_of


# -- markdown -------------------------------------------------------------------------------------------------------
def _rate(stats: Mapping[str, Any]) -> str:
    lo, hi = stats["interval"]
    return f"{stats['rate']:.1f} % [{lo:.0f}, {hi:.0f}]"


def markdown(analysis: Mapping[str, Any], name: str = "the evaluation", versus_name: str = "the other",
             attributes: Sequence[str] | None = None) -> str:
    """The analysis as markdown: a table per attribute (worst first), the confusion matrices (counts, with each
    row's rate of reading what was named), and the versus table where there is one."""
    lines = [f"{name}: {analysis['n']} episodes, {analysis['successes']} successes "
             f"({100.0 * analysis['successes'] / max(1, analysis['n']):.1f} %). Rates with their 95 % interval.", ""]
    for attribute in attributes or ATTRIBUTES:
        found = analysis["slices"][attribute]
        if set(found) == {NOT_READ}:
            lines += [f"**{ATTRIBUTES[attribute]}**: not read (no recorded maps)", ""]
            continue
        lines += [f"| {ATTRIBUTES[attribute]} | episodes | successes | success |", "|---|---:|---:|---:|"]
        lines += [f"| {value} | {s['n']} | {s['successes']} | {_rate(s)} |" for value, s in found.items()]
        lines.append("")
    for which, title in (("confusion", "unambiguous instructions"), ("confusion_ambiguous", "ambiguous instructions")):
        for matrix, what in CONFUSIONS.items():
            m = analysis[which][matrix]
            if not m:
                continue
            lines += [f"**{what}** ({title}): the reading, most frequent first; \"right\": the share read as asked",
                      "", "| asked | episodes | right | read as |", "|---|---:|---:|---|"]
            for asked, reads in m.items():
                n = sum(reads.values())
                read = ", ".join(f"{k} {v}" for k, v in reads.items())
                lines.append(f"| {asked} | {n} | {100.0 * reads.get(asked, 0) / n:.0f} % | {read} |")
            lines.append("")
    if "versus" in analysis:
        summary = analysis["versus_summary"]
        o = summary["overall"]
        lines += [f"{name} against {versus_name} on the {summary['n']} environments both flew: {o['rate']:.1f} % "
                  f"against {o['rate_versus']:.1f} %, {o['fixed']} fixed and {o['broken']} broken (sign test "
                  f"p = {o['p']:.3g}). The slices that differ most, those significant after Holm's correction for the "
                  f"{summary['tested']} slices tested first:", "",
                  "| slice | episodes | success | versus | fixed | broken | p | p, corrected |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for s in summary["largest"]:
            where = ", ".join(f"{ATTRIBUTES[a]}: {v}" for a, v in s["slice"].items())
            lines.append(f"| {where} | {s['n']} | {s['rate']:.1f} % | {s['rate_versus']:.1f} % | {s['fixed']} | "
                         f"{s['broken']} | {s['p']:.3g} | {s['p_adjusted']:.3g} |")
        lines.append("")
    return "\n".join(lines)
