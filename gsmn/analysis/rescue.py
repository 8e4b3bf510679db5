"""Map codes from calibration flights, and rescue rates: how many of an evaluation's failures each truth
intervention saves, per attributed stage (docs/model.md, "Interventions"; docs/results.md, "Rescue rates").

A causal check of failure attribution: a failure attributed to grounding should be rescued by perfect grounding
far more often than by perfect perception. Each failure is flown again with each intervention from its first step;
its stage comes from the evaluation (an episode's "stage"), else from its recorded maps (`--record`), else from one
more flight without intervention that records them (which also shows whether the failure replays as a failure; one
that succeeds on replay is left out and counted apart).
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

from gsmn.analysis.intervention import (
    CODES_FILE,
    FLAGS,
    InterventionError,
    MapCodes,
    derive_codes,
    intervention_from_flag,
    weights_digest,
)
from gsmn.analysis.slices import wilson
from gsmn.analysis.truth import truth_maps
from gsmn.attribution import PIPELINE, Heads, attribute_record, load_trace, trace_path
from gsmn.config import RunConfig
from gsmn.evaluation import PartialResults, checkpoint_fingerprint, evaluate, results_dict, write_json
from gsmn.model.checkpoint import load_checkpoint, read_checkpoint_kind
from gsmn.task.rollout import EpisodeRecord, task_for_env

CALIBRATION_EPISODES = 40


def calibrate(folder: Path | str, env_ids: Sequence[int], config: RunConfig, workers: int = 1,
              on_episode: Callable[[EpisodeRecord], None] | None = None) -> MapCodes:
    """Fly the checkpoint on `env_ids` (dev environments: never the test ones), record its final maps, and derive
    its `MapCodes` from them; written beside the weights as map_codes.safetensors by `save_codes`."""
    folder = Path(folder)
    kind = read_checkpoint_kind(folder)
    if kind not in ("gsmn", "gsmn-no-plan"):
        raise InterventionError(f"map codes are a GSMN's; {folder} holds a {kind!r} model")
    model, *_ = load_checkpoint(folder)
    heads = Heads.of(model)
    n = model.config.model.map_size
    with tempfile.TemporaryDirectory(prefix="gsmn-codes-") as tmp:
        records = evaluate(kind, env_ids, config, folder, workers, on_episode=on_episode, record_dir=tmp)
        finals = []
        for record in records:
            maps = load_trace(trace_path(tmp, record.env_id)).maps
            task = task_for_env(record.env_id, config)
            truth = truth_maps(task.world, task.instruction, n, config.task.success_radius)
            finals.append((truth, maps.semantic_map_w, maps.relevance_map_w, maps.goal_map_w, record.success))
    meta = {"env_ids": [int(e) for e in env_ids], "weights_sha256": weights_digest(folder),
            "command": f"gsmn map-codes --checkpoint {folder} --episodes {len(env_ids)}"}
    return derive_codes(finals, heads, meta)


def save_codes(folder: Path | str, codes: MapCodes) -> Path:
    path = Path(folder) / CODES_FILE
    codes.save(path)
    return path


def failures_of(results: dict) -> list[dict]:
    """The failed episodes of an evaluation file (full or compact)."""
    episodes = results.get("episodes") if isinstance(results, dict) else None
    if not isinstance(episodes, list):
        raise ValueError("not an evaluation: no list of episodes (a `gsmn eval --json` file or a compact evaluation)")
    return [e for e in episodes if not e.get("success")]


def stages_of(failures: Sequence[dict], folder: Path | str, config: RunConfig, record: Path | str | None = None,
              workers: int = 1, on_episode=None) -> tuple[dict[int, str], list[int]]:
    """Each failure's attributed stage by env id, and the env ids that succeeded when flown again (no stage)."""
    stages = {int(e["env_id"]): e["stage"] for e in failures if e.get("stage")}
    todo = [e for e in failures if int(e["env_id"]) not in stages]
    if not todo:
        return stages, []
    model, *_ = load_checkpoint(folder)
    heads = Heads.of(model)
    replayed: list[int] = []
    if record is None:  # fly them again, recording the maps
        record = tempfile.mkdtemp(prefix="gsmn-rescue-")
        kind = read_checkpoint_kind(folder)
        flown = evaluate(kind, [int(e["env_id"]) for e in todo], config, folder, workers, on_episode=on_episode,
                         record_dir=record)
        replayed = [r.env_id for r in flown if r.success]
        todo = [r.to_dict() for r in flown if not r.success]
    for episode in todo:
        path = trace_path(record, int(episode["env_id"]))
        if not path.is_file():
            raise ValueError(f"no recorded maps for environment {episode['env_id']} in {record}: give the "
                             "evaluation's --record folder, or leave --record out to fly the failures again")
        stages[int(episode["env_id"])] = attribute_record(episode, load_trace(path), heads, config).stage
    return stages, replayed


def fly_intervention(flag: str, env_ids: Sequence[int], folder: Path | str, config: RunConfig, out: Path,
                     workers: int = 1, on_episode=None) -> list[EpisodeRecord]:
    """Fly `env_ids` with the intervention `flag`, kept episode by episode in out/FLAG.json.partial.jsonl (a stopped
    run resumes), written to out/FLAG.json at the end."""
    intervention = intervention_from_flag(flag)
    kind = read_checkpoint_kind(folder)
    fingerprint = checkpoint_fingerprint(kind, str(folder))
    path = Path(out) / f"{flag}.json"
    if path.is_file():  # flown before: kept when it is the same checkpoint on the same environments
        kept = json.loads(path.read_text())
        if kept.get("env_ids") == list(env_ids) and kept.get("fingerprint") == fingerprint:
            return [EpisodeRecord.from_dict(e) for e in kept["episodes"]]
    partial = PartialResults(path)
    done = partial.open({"intervention": flag, "env_ids": list(env_ids), "fingerprint": fingerprint,
                         "config": config.to_dict()}, resume=True)
    done_ids = {r.env_id for r in done}

    def keep(record: EpisodeRecord) -> None:
        partial.append(record)
        if on_episode is not None:
            on_episode(record)

    flown = evaluate(kind, [e for e in env_ids if e not in done_ids], config, folder, workers, on_episode=keep,
                     intervention=intervention)
    by_id = {r.env_id: r for r in done + flown}
    records = [by_id[e] for e in env_ids]
    results = results_dict(kind, str(folder), records, config, 0.0, workers)
    results.update(intervention=intervention.to_dict(), fingerprint=fingerprint)
    write_json(path, results)
    partial.remove()
    return records


def rescue_table(stages: dict[int, str | None], flown: dict[str, Iterable[tuple[int, bool]]],
                 replayed: Sequence[int] = ()) -> dict:
    """Rescue rates: per intervention (its flights as (env_id, success) pairs), the failures it turned into
    successes, over all and per attributed stage, with 95 % Wilson intervals; a failure it has not flown (yet) is
    not counted in its row ("of" says how many it flew)."""
    by_stage: dict[str, list[int]] = {}
    for env_id, stage in sorted(stages.items()):
        by_stage.setdefault(stage or "not read", []).append(env_id)
    order = {stage: k for k, stage in enumerate(PIPELINE)}  # the pipeline's order, as the attribution bars
    by_stage = dict(sorted(by_stage.items(), key=lambda kv: (order.get(kv[0], len(order)), kv[0])))

    def rate(k: int, n: int) -> dict:
        lo, hi = wilson(k, n)
        return {"rescued": k, "of": n, "rate": k / n if n else None, "low": lo, "high": hi}

    table = {}
    for flag, pairs in flown.items():
        outcome = dict(pairs)
        saved = {e for e, success in outcome.items() if success}
        table[flag] = {"all": rate(len(saved & set(stages)), len(set(outcome) & set(stages))),
                       "per_stage": {s: rate(len(saved & set(ids)), len(set(outcome) & set(ids)))
                                     for s, ids in by_stage.items()}}
    return {"failures": len(stages), "stages": {s: len(ids) for s, ids in by_stage.items()},
            "succeeded_on_replay": sorted(int(e) for e in replayed), "interventions": table}


def rescue_markdown(table: dict) -> str:
    flags = list(table["interventions"])
    stages = list(table["stages"])
    head = "| attributed stage | failures | " + " | ".join(flags) + " |"
    lines = [head, "|" + "---|" * (2 + len(flags))]

    def cell(r: dict) -> str:
        if not r["of"]:
            return "-"
        return f"{r['rescued']} ({100 * r['rate']:.0f} %, {100 * r['low']:.0f}-{100 * r['high']:.0f})"

    for s in stages:
        lines.append(f"| {s} | {table['stages'][s]} | "
                     + " | ".join(cell(table["interventions"][f]["per_stage"][s]) for f in flags) + " |")
    lines.append(f"| all | {table['failures']} | " + " | ".join(cell(table["interventions"][f]["all"]) for f in flags)
                 + " |")
    if table["succeeded_on_replay"]:
        lines.append("")
        lines.append(f"{len(table['succeeded_on_replay'])} failure(s) succeeded when flown again and are left out: "
                     + ", ".join(map(str, table["succeeded_on_replay"])))
    return "\n".join(lines)


__all__ = ["FLAGS", "calibrate", "failures_of", "fly_intervention", "rescue_markdown", "rescue_table", "save_codes",
           "stages_of"]
