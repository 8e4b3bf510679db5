"""An evaluation analysed across all its episodes (`gsmn.analysis.slices`) from the dashboard's record: slices,
confusion matrices, two evaluations of the same environments compared slice by slice, and the episodes behind every
number.

Each episode's facts (its world's and its end's attributes, and the readings of its maps) are kept in the record's
`episode_facts` table: written when the episode is recorded (`facts_of`, called by `EpisodeRecorder`), and for an
evaluation recorded before the table existed computed from its rows the first time it is analysed, then kept. An
analysis of a finished evaluation is a pure function of its rows, so it is kept in memory once computed.

The shipped evaluations (`shipped`: the shipped GSMN's on Table 1's test environments, checkpoints/gsmn/table1.json,
and Table 2's on dev and on test, checkpoints/table2/*/evaluation.json and table1.json) are offered without an
evaluation run: asked for, one is imported into the record once, as a finished
evaluation of its checkpoint (its episodes' attributed stages and facts as the file keeps them), so its episodes list,
replay and analyse like any other.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from app.jobs.db import FINISHED, Database, EpisodeRow, Evaluation, RecordError
from app.live.commands import NotFound, RunnerError
from gsmn.analysis import slices
from gsmn.analysis.intervention import FLAG_LABELS
from gsmn.config import RunConfig

log = logging.getLogger("gsmn.dashboard")

SHIPPED_SOURCE = "import"
SPLIT_NAMES = {"evaluation.json": ("dev", "dev environments (Table 2)"),
               "table1.json": ("test", "test environments (Table 1)")}


def facts_of(record: dict, config: RunConfig, attribution: dict | None) -> dict:
    """The facts of an evaluated episode (`gsmn eval`'s record or progress line) and its attribution."""
    from gsmn.world.spec import world_for_env

    world = world_for_env(int(record["env_id"]), config.world)
    return slices.episode_facts(record, world, attribution, config.task.success_radius)


def row_facts(row: EpisodeRow, config: RunConfig) -> dict | None:
    """The facts of a recorded episode, from its environment's world and instruction (None where the environment's
    instruction is not the one recorded: it cannot be rebuilt)."""
    from gsmn.task.instructions import instruction_for_env
    from gsmn.world.spec import world_for_env

    world = world_for_env(row.env_id, config.world)
    instruction = instruction_for_env(world, config.task)
    if instruction.text != row.instruction:
        return None
    record = {"env_id": row.env_id, "landmark_index": instruction.landmark_index, "goal_x": instruction.goal_x,
              "goal_y": instruction.goal_y, "final_x": row.final_x, "final_y": row.final_y}
    return slices.episode_facts(record, world, row.attribution, config.task.success_radius)


@dataclass(frozen=True)
class Shipped:
    """An evaluation shipped with the project."""

    key: str  # "table2/no-percept/dev"
    label: str
    path: Path
    checkpoint: Path
    system: str  # the model kind it flew as
    split: str


def shipped(root: Path) -> list[Shipped]:
    """The evaluations shipped under `root` (the checkpoints folder): the shipped GSMN's on Table 1's test
    environments (gsmn/table1.json, with its maps' readings), then Table 2's systems in their table's order."""
    from gsmn.experiments.recipe import SYSTEMS

    out = []
    if (root / "gsmn" / "table1.json").is_file():
        out.append(Shipped("gsmn/test", "GSMN, the shipped checkpoint: test environments (Table 1)",
                           root / "gsmn" / "table1.json", root / "gsmn", "gsmn", "test"))
    for system in SYSTEMS:
        for name, (split, where) in SPLIT_NAMES.items():
            path = root / "table2" / system.name / name
            if path.is_file():
                out.append(Shipped(f"table2/{system.name}/{split}", f"{system.label}, Table 2's recipe: {where}",
                                   path, path.parent, system.kind, split))
    return out


class Analyses:
    """The analyses of the record's evaluations (thread-safe; kept once computed for finished evaluations)."""

    def __init__(self, db: Database, config: RunConfig, checkpoints: Path):
        self.db, self.config, self.checkpoints = db, config, checkpoints
        self._lock = threading.Lock()  # the analyses kept
        self._importing = threading.Lock()  # two tabs asking for one shipped evaluation at once import it once
        self._kept: dict[tuple[int, int | None], dict] = {}

    # -- rows ---------------------------------------------------------------------------------------------------
    def evaluation(self, evaluation_id: int) -> Evaluation:
        e = self.db.evaluation(evaluation_id)
        if e is None:
            raise NotFound(f"no evaluation {evaluation_id}")
        return e

    def rows(self, e: Evaluation, episodes: list[EpisodeRow] | None = None) -> list[dict]:
        """The evaluation's episodes (read when not given) as `slices` reads them, with their facts (computed and
        kept where missing)."""
        episodes = self.db.episodes(e.id) if episodes is None else episodes
        kept = {env: f for env, f in self.db.facts(e.id).items() if slices.valid_facts(f)}  # else computed again
        missing = {}
        config = self._config(e)
        for row in episodes:
            if row.env_id not in kept:
                found = row_facts(row, config)
                if found is not None:
                    missing[row.env_id] = kept[row.env_id] = found
        if missing and e.status == FINISHED:
            try:
                self.db.set_facts(e.id, missing)
            except RecordError as err:  # a full disk: answered all the same, computed again next time
                log.warning("facts of evaluation %d not kept: %s", e.id, err)
        return [slices.normalise({**row.__dict__, "facts": kept.get(row.env_id)}) for row in episodes]

    def _config(self, e: Evaluation) -> RunConfig:
        if e.folder:
            try:
                return RunConfig.from_dict(json.loads((Path(e.folder) / "config.json").read_text()))
            except (OSError, ValueError, TypeError):
                pass
        return self.config

    # -- analyses -----------------------------------------------------------------------------------------------
    def analysis(self, evaluation_id: int, versus_id: int | None = None) -> dict:
        """`slices.analyze` of an evaluation (and against `versus_id`), with what was compared with what."""
        e = self.evaluation(evaluation_id)
        other = self.evaluation(versus_id) if versus_id is not None else None
        key = (e.id, other.id if other else None)
        with self._lock:
            if key in self._kept:
                return self._kept[key]
        rows = self.rows(e)
        out = slices.analyze(rows, self.rows(other) if other else None)
        out["evaluation"] = describe(e)
        if other is not None:
            out["versus_evaluation"] = describe(other)
            if out["versus_summary"]["n"] == 0:
                raise RunnerError(f"evaluations {e.id} and {other.id} share no environment: nothing to compare")
        out["warnings"] = warnings(e, other)
        if e.status == FINISHED and (other is None or other.status == FINISHED):
            with self._lock:
                self._kept[key] = out
        return out

    def episodes(self, evaluation_id: int, criteria: dict[str, str] | None = None,
                 cell: tuple[str, str, str] | None = None, ambiguous: bool | None = None,
                 versus_id: int | None = None) -> list[EpisodeRow]:
        """The episodes behind a number of the analysis: `slices.select`, as the record's rows, in the order flown;
        with `versus_id` (a number of the versus table) only those of environments both evaluations flew."""
        for attribute in criteria or {}:
            if attribute not in slices.ATTRIBUTES:
                raise RunnerError(f"no attribute {attribute!r}; choose from {', '.join(slices.ATTRIBUTES)}")
        if cell is not None and cell[0] not in slices.CONFUSIONS:
            raise RunnerError(f"no confusion matrix {cell[0]!r}; choose from {', '.join(slices.CONFUSIONS)}")
        e = self.evaluation(evaluation_id)
        episodes = self.db.episodes(e.id)
        chosen = set(slices.select(self.rows(e, episodes), criteria, cell, ambiguous))
        if versus_id is not None:
            chosen &= set(self.evaluation(versus_id).env_ids)
        return [row for row in episodes if row.env_id in chosen]

    # -- shipped evaluations ----------------------------------------------------------------------------------
    def shipped(self, evaluations: list[Evaluation] | None = None) -> list[dict]:
        """The shipped evaluations, each with the id of its evaluation in the record once imported (else None), from
        the record's `evaluations` (read when not given)."""
        evaluations = self.db.evaluations() if evaluations is None else evaluations
        imported = {e.folder: e.id for e in evaluations if e.source == SHIPPED_SOURCE and e.folder}
        return [{"key": s.key, "label": s.label, "split": s.split, "evaluation_id": imported.get(str(s.path))}
                for s in shipped(self.checkpoints)]

    def import_shipped(self, key: str) -> Evaluation:
        """The record's evaluation of a shipped evaluation, imported the first time it is asked for."""
        found = {s.key: s for s in shipped(self.checkpoints)}
        if key not in found:
            raise NotFound(f"no shipped evaluation {key!r}; choose from {', '.join(found) or 'none'}")
        s = found[key]
        with self._importing:
            imported = {e.folder: e for e in self.db.evaluations() if e.source == SHIPPED_SOURCE and e.folder}
            e = imported.get(str(s.path)) or self._import(s.path, s.system, s.checkpoint, s.label)
            for path in sorted((s.path.parent / "rescue").glob("truth-*.json")) if s.split == "test" else ():
                if str(path) not in imported:  # its failures flown with a true map (`gsmn analyze rescue`)
                    self._import(path, s.system, s.checkpoint, None, e)
            return e

    def _import(self, path: Path, system: str, checkpoint: Path, label: str | None,
                rescued: Evaluation | None = None) -> Evaluation:
        try:
            results = json.loads(path.read_text())
            rows = slices.with_facts(results)  # the facts the file keeps, else computed here
            episodes = [EpisodeRow(
                evaluation_id=0, position=position, env_id=row["env_id"], instruction=ep["instruction"],
                landmark=row["landmark"], side=row["side"], ambiguous=row["ambiguous"], success=row["success"],
                landmark_success=row["landmark_success"], goal_distance=float(ep["goal_distance"]),
                steps=row["steps"], stopped=row["stopped"], final_x=float(ep["final_x"]), final_y=float(ep["final_y"]),
                stage=row["stage"], attribution=None, recording=None)
                for position, (ep, row) in enumerate(zip(results["episodes"], rows, strict=True))]
            flag = f"truth-{results['intervention']['map']}" if rescued is not None else None
        except (OSError, ValueError, KeyError, TypeError, IndexError) as err:
            raise RunnerError(f"{path} is not a readable evaluation: {type(err).__name__}: {err}") from err
        if rescued is not None:
            label = f"the {len(rows)} failures of #{rescued.id}, {FLAG_LABELS.get(flag, flag)} (shipped)"
        now = time.time()
        eid = self.db.add_whole_evaluation(  # all or nothing: a server killed meanwhile leaves no half evaluation
            {"status": FINISHED, "created": now, "started": now, "finished": now, "system": system,
             "checkpoint": str(checkpoint), "env_ids": [row["env_id"] for row in rows], "label": label,
             "source": SHIPPED_SOURCE, "folder": str(path), "total": len(rows), "done": len(rows),
             "summary": results.get("summary"), "intervention": flag,
             "baseline_id": rescued.id if rescued is not None else None},
            episodes, {row["env_id"]: row["facts"] for row in rows})
        return self.db.evaluation(eid)


def describe(e: Evaluation) -> dict:
    return {"id": e.id, "label": e.label, "system": e.system, "checkpoint": e.checkpoint, "episodes": e.total,
            "status": e.status}


def warnings(e: Evaluation, other: Evaluation | None) -> list[str]:
    """What a reader of the numbers must know: environments trained on, test environments, fewer shared."""
    from gsmn.world.spec import split_of

    out = []
    for which in (e, other):
        if which is None:
            continue
        splits = {split_of(i) for i in which.env_ids}
        if "train" in splits:
            out.append(f"Evaluation {which.id} flew training environments: the model may have learned them.")
        if "test" in splits:
            out.append(f"Evaluation {which.id} flew test environments: choosing a model by these numbers spends the "
                       "test set.")
    if other is not None:
        shared = set(e.env_ids) & set(other.env_ids)
        if len(shared) < max(len(e.env_ids), len(other.env_ids)):
            out.append(f"The two evaluations share {len(shared)} environments; only those are compared.")
    return out
