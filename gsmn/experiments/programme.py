"""The Table 2 programme (the paper's development results): the systems of `gsmn.experiments.recipe` (GSMN, its four
objective ablations and GSMN observing noisy poses, the original code's two module ablations, and Table 1's
first-person baselines), trained with one recipe and flown on the same dev environments; `gsmn experiment table2
--out DIR` (`gsmn.experiments.table2`) runs it all and resumes it wherever it stopped, and the tables of what it
keeps are `gsmn.experiments.table`'s.

Each system is the control's configuration with one switch changed, or a baseline's kind (`SYSTEMS`); everything
else (the expert data, epochs, DAggerFM schedule, seeds, evaluation) is the `Recipe`'s, the same for all. Per
system, in order:

    supervised   `recipe.epochs` epochs on the expert data of `recipe.train_envs` train environments
    dagger       `recipe.iterations` DAggerFM iterations in fresh train environments (the ones after the first
                 `recipe.train_envs`), from the supervised checkpoint, with Adam started afresh
    evaluate     flown plainly on the first `recipe.eval_envs` dev environments with the maps recorded, each failure
                 attributed to a stage (gsmn.attribution)
    table 1      the control, -J_plan and the baselines (`TABLE1`) also on Table 1's first `recipe.table1_envs` test
                 environments, once the control's dev success has passed `recipe.control_gate` (below it, no further
                 system starts: the recipe is extended for all, and a run goes on from its saved state to the longer
                 end)

Surviving the loss of the machine. `runs/` and `data/` may be gone at the next start. The expert data is rebuilt by
collection (deterministic by environment id). Each system's latest finished stage (every `publish_every_epochs`
supervised epochs, the end of supervised learning, every `publish_every_iterations` DAggerFM iterations, the end)
is copied to `SHIP/<name>/` (a checkpoint folder: weights, config, vocabulary, meta and Adam state as safetensors,
plus the run's small JSON files in `run/`; never images, never a pickle), replacing the previous copy; with
`git_commit` it is committed when a stage ends (the last supervised epoch, the last DAggerFM iteration, an
evaluation), and `--keep-latest --git-commit` commits it, with any partial evaluation, before the work pauses: one
committed resume copy per system, replaced. A finished system's copy keeps no Adam state.
Every finished epoch and iteration is also copied to `OUT/<name>/latest` (not committed):
`--keep-latest` ships those over the stage copies on demand, before a machine is given up between two of them.
A start whose run folder is behind that copy restores the run from it and goes on; a DAggerFM run restored this
way has no dataset and refills it from the current mixture policy (gsmn.training.dagger). The finished evaluation
is kept there too, compactly (`evaluation.json`, `table1.json`: one line of figures per episode, no trajectories),
so the tables need nothing else; a further stage copy (a recipe extended since) replaces them, not yet evaluated.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gsmn.config import RunConfig
from gsmn.experiments.recipe import (
    BY_NAME,
    EVALUATIONS,
    SYSTEMS,
    TABLE1,
    Recipe,
    System,
    chunk_tag,
    describe_stage,
    environments,
    finished,
    kept_partial,
    partial_path,
    read_stage,
    stage_key,
    stage_order,
    system_configs,
    trained,
)
from gsmn.experiments.table import table_markdown
from gsmn.model.checkpoint import LEGACY_OPTIMIZER_FILE, OPTIMIZER_FILE, optimizer_file

# environments flown between two kept partial evaluations (committed with --git-commit): a lost machine loses fewer
EVAL_CHUNK = 50


def write_stage(ship: Path, stage: dict) -> None:
    """Write a stage copy's stage.json atomically: a kill leaves the old one or the new one."""
    tmp = ship / f".stage.json.tmp{os.getpid()}"
    tmp.write_text(json.dumps(stage, indent=1, sort_keys=True) + "\n")
    tmp.replace(ship / "stage.json")


def _state_epoch(run_root: Path) -> int:
    """Finished epochs (iterations) of a run folder's saved state; -1 without one."""
    for name in ("state", "state.old"):
        try:
            return int(json.loads((run_root / name / "state.json").read_text())["epoch"])
        except (OSError, ValueError, KeyError):
            continue
    return -1


SUPERVISED_LOG = "supervised_log.jsonl"  # in a DAggerFM stage copy's run/: the supervised run's log.jsonl


def publish(run_root: Path, ship: Path, stage: dict, supervised_log: Path | None = None) -> None:
    """Replace the copy at `ship` with the run's checkpoint and its small state files (atomically: a kill leaves
    the old copy or the new one); a DAggerFM copy keeps the supervised run's log beside its own (`SUPERVISED_LOG`),
    so the per-epoch dev figures outlive the supervised run folder."""
    ship.parent.mkdir(parents=True, exist_ok=True)
    tmp = ship.parent / f".{ship.name}.tmp{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    # a finished system ships weights, config, vocabulary and meta: no optimizer state (nothing resumes it)
    shutil.copytree(run_root / "checkpoint", tmp,
                    ignore=shutil.ignore_patterns(OPTIMIZER_FILE, LEGACY_OPTIMIZER_FILE) if trained(stage) else None)
    (tmp / "run").mkdir()
    for name, source in (("config.json", run_root / "config.json"), ("log.jsonl", run_root / "log.jsonl"),
                         ("state.json", run_root / "state" / "state.json")):
        shutil.copy2(source, tmp / "run" / name)
    if supervised_log is not None:
        shutil.copy2(supervised_log, tmp / "run" / SUPERVISED_LOG)
    evaluated = _carry_evaluations(ship, tmp, stage)
    write_stage(tmp, {**stage, "evaluated": evaluated})
    _swap(tmp, ship)


def _carry_evaluations(ship: Path, tmp: Path, stage: dict) -> bool:
    """Copy the evaluations of the stage copy at `ship` into its replacement `tmp` where both are the same stage;
    a further stage (a recipe extended since) is a new model, not yet evaluated. Returns whether `tmp` is evaluated."""
    if stage_key(read_stage(ship)) != stage_key(stage):
        return False
    for split in EVALUATIONS:
        for path in (ship / EVALUATIONS[split][1], partial_path(ship, split)):
            if path.is_file():
                shutil.copy2(path, tmp / path.name)
    return (tmp / "evaluation.json").is_file()


def _swap(tmp: Path, ship: Path) -> None:
    """Put the folder `tmp` at `ship` in place of what is there."""
    old = ship.parent / f".{ship.name}.old{os.getpid()}"
    shutil.rmtree(old, ignore_errors=True)
    if ship.exists():
        ship.rename(old)
    tmp.rename(ship)
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def ship_lock(ship: Path):
    """Held while a stage copy is compared and replaced (`keep_latest`, a running system's `keep`), so that two
    writers never interleave: a lock on the folder of the stage copies itself (no lock file), which the kernel lets
    go when its holder dies."""
    ship.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(ship.parent, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def keep_latest(layout: Layout, systems: list[System], commit: bool = False, log=print) -> list[str]:
    """Copy each system's last finished epoch or iteration (OUT/<name>/latest, written at every one) over its stage
    copy where it is further on, and commit it: for a machine about to be lost between two stage copies. Safe
    while the programme runs (both swap whole folders). Returns the names of the systems copied."""
    kept = []
    for system in systems:
        latest, ship = layout.latest(system), layout.shipped(system)
        with ship_lock(ship):
            new, old = read_stage(latest), read_stage(ship)
            if new is None or stage_order(new) <= stage_order(old):
                log(f"{system.name}: its stage copy is up to date" if new is not None else
                    f"{system.name}: no finished epoch in {latest}")
                new = None
            else:
                tmp = ship.parent / f".{ship.name}.tmp{os.getpid()}"
                shutil.rmtree(tmp, ignore_errors=True)
                shutil.copytree(latest, tmp)  # further on: not yet evaluated (its stage.json says so)
                _swap(tmp, ship)
        stage = read_stage(ship)
        if stage is None:
            continue
        what = "epoch" if stage.get("stage") == "supervised" else "iteration"
        where = f"{'supervised' if stage.get('stage') == 'supervised' else 'dagger'} {what} {stage['epoch']} of " \
                f"{stage['epochs']}"
        if new is not None:
            log(f"{system.name}: kept {where} in {ship}")
            kept.append(system.name)
        partial = [(split, kept_partial(ship, split)) for split in EVALUATIONS]
        flown = [f"{len(p['episodes'])} of {len(p['env_ids'])} {split} environments flown" for split, p in partial
                 if p["episodes"]]  # an evaluation under way: its finished chunks
        message = f"table2: {system.label}, " + (", ".join(flown) + " (partial evaluation, for resuming)" if flown
                                                  else f"{where} (stage copy for resuming)")
        if commit:  # the one committed resume copy, replaced: committed when a stage ends or the work pauses
            git_commit([ship], message, log)  # nothing to commit where the copy is committed already
    return kept


def restore(ship: Path, run_root: Path) -> None:
    """Rebuild a run folder from a stage copy: its config, log, checkpoint and resumable state."""
    shutil.rmtree(run_root, ignore_errors=True)
    (run_root / "state").mkdir(parents=True)
    shutil.copy2(ship / "run" / "config.json", run_root / "config.json")
    shutil.copy2(ship / "run" / "log.jsonl", run_root / "log.jsonl")
    shutil.copy2(ship / "run" / "state.json", run_root / "state" / "state.json")
    shutil.copy2(ship / "weights.safetensors", run_root / "state" / "weights.safetensors")
    optimizer = optimizer_file(ship)
    if optimizer is None:
        raise ValueError(f"{ship} holds no optimizer state: a finished system's copy cannot be trained further")
    shutil.copy2(optimizer, run_root / "state" / optimizer.name)
    checkpoint = run_root / "checkpoint"
    shutil.copytree(ship, checkpoint, ignore=shutil.ignore_patterns("run", "stage.json", "evaluation.json"))


def git_commit(paths: list[Path], message: str, log=print, tries: int = 6) -> bool:
    """Commit `paths` (and only them) to the repository they are in; retried while another git command holds the
    index. Returns whether it committed."""
    top = subprocess.run(["git", "-C", str(paths[0].parent), "rev-parse", "--show-toplevel"], capture_output=True,
                         text=True)
    if top.returncode != 0:
        log(f"not committed: {paths[0]} is not in a git repository")
        return False
    cwd, rel = top.stdout.strip(), [os.path.relpath(p, top.stdout.strip()) for p in paths]
    error = ""
    for attempt in range(tries):
        add = subprocess.run(["git", "add", "-A", "--", *rel], cwd=cwd, capture_output=True, text=True)
        if add.returncode == 0:
            staged = subprocess.run(["git", "diff", "--cached", "--quiet", "--", *rel], cwd=cwd)
            if staged.returncode == 0:
                return True  # nothing changed
            done = subprocess.run(["git", "commit", "-q", "-m", message, "--", *rel], cwd=cwd, capture_output=True,
                                  text=True)
            if done.returncode == 0:
                return True
            error = done.stderr.strip()
        else:
            error = add.stderr.strip()
        time.sleep(5 * (attempt + 1))  # e.g. another command's index.lock, or a merge in progress
    log(f"not committed after {tries} tries ({error}); the copy is in {paths[0]}: commit it by hand")
    return False


# -- one system -----------------------------------------------------------------------------------------------
@dataclass
class Layout:
    out: Path  # run folders and data (may be lost)
    ship: Path  # stage copies and evaluations (committed)

    @property
    def data(self) -> Path:
        return self.out / "data"

    def run(self, system: System, stage: str) -> Path:
        return self.out / system.name / stage

    def shipped(self, system: System) -> Path:
        return self.ship / system.name

    def latest(self, system: System) -> Path:
        """The last finished epoch's copy, in the layout of a stage copy (written every epoch, never committed)."""
        return self.out / system.name / "latest"


STORES = {"train": "the supervised data", "dev": "the dev data", "seed": "the DAggerFM seed data"}


def collect_store(layout: Layout, recipe: Recipe, name: str, workers: int = 1, log=print,
                  progress: Path | None = None) -> None:
    """The expert store `name` (`STORES`), collected by a system when its next stage reads it, not up front: a start
    on a new machine during DAggerFM or evaluation then flies only the dev data, not the 600 supervised episodes that
    systems still to come will read. Two systems arriving together share the work: the one that holds the lock on
    `expert_<name>.lock` flies the ids from the first, the other from the last, each skipping an episode already
    written when it comes to it, so they meet in the middle (deterministic by environment id, so an episode flown
    twice is the same file; a third collector would go the second's way and duplicate its work). `progress` gets
    {"store", "done", "total"} as episodes are written, for the programme's bars, and is removed at the end."""
    from gsmn.evaluation import write_json
    from gsmn.training.collect import collect_expert, episode_key
    from gsmn.training.store import EpisodeStore

    ids = environments(recipe)[name]
    store = EpisodeStore(layout.data / f"expert_{name}")
    missing = [e for e in ids if episode_key(e) not in store]
    if not missing:
        return
    config = recipe.base_config()

    def on_episode(*_) -> None:
        if progress is not None:
            write_json(progress, {"store": name, "done": len(store), "total": len(ids)})  # the store holds only ids

    with open(layout.data / f"expert_{name}.lock", "a") as lock:  # the kernel lets it go when its holder dies
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            forward = True
        except BlockingIOError:
            forward = False  # another system is collecting from the first id
        log(f"collecting {STORES[name]}: {len(missing)} of {len(ids)} expert episodes to go, "
            f"{'first' if forward else 'last'} ids first")
        try:
            on_episode()
            collect_expert(store, missing if forward else missing[::-1], config, workers=workers,
                           on_episode=on_episode)
        finally:
            if progress is not None:
                progress.unlink(missing_ok=True)


def data_needed(layout: Layout, recipe: Recipe, systems: list[System]) -> tuple[str, ...]:
    """The expert stores the remaining stages of `systems` read."""
    needed = set()
    for system in systems:
        stage = read_stage(layout.shipped(system)) or {}
        dagger_epoch = max(stage.get("epoch", -1) if stage.get("stage") == "dagger" else -1,
                           _state_epoch(layout.run(system, "dagger")))
        if dagger_epoch < recipe.iterations:  # the evaluation flies environments; it reads no expert data
            needed.add("dev")
        in_dagger = dagger_epoch >= 0
        if not in_dagger:
            needed.add("seed")
            if stage.get("stage") != "supervised" or stage.get("epoch", 0) < recipe.epochs:
                needed.add("train")
    return tuple(n for n in ("train", "dev", "seed") if n in needed)


def run_system(system: System, layout: Layout, recipe: Recipe, threads: int = 2, commit: bool = False,
               log=print, on_progress=None, stop_after=None, device: str = "cpu") -> dict | None:
    """Train and evaluate one system, resuming from its run folders or its stage copy; returns its evaluation, or
    None when `stop_after(stage, state)` ("supervised" or "dagger", the run's TrainState after a saved epoch) ended
    it early (the stage copy made by then is kept).

    A stage copy further on than this run (trained on another machine and shipped with `--keep-latest` meanwhile)
    is never replaced by this run's older one: the run stops at that epoch's end and goes on from the copy."""
    while True:
        superseded: list[str] = []
        result = _run_system_once(system, layout, recipe, threads, commit, log, on_progress, stop_after, device,
                                  superseded)
        if not superseded:
            return result
        log(f"{system.name}: going on from the further stage copy in {layout.shipped(system)}")


def _run_system_once(system: System, layout: Layout, recipe: Recipe, threads: int, commit: bool, log, on_progress,
                     stop_after, device: str, superseded: list[str]) -> dict | None:
    from gsmn.evaluation import write_json
    from gsmn.training.dagger import train_dagger
    from gsmn.training.store import EpisodeStore
    from gsmn.training.supervised import train_supervised

    ship = layout.shipped(system)
    if done(layout, system, recipe):
        return json.loads((ship / "evaluation.json").read_text())
    sup_config, dagger_config = system_configs(system, recipe, threads, device)
    sup_run, dagger_run = layout.run(system, "supervised"), layout.run(system, "dagger")
    stage = read_stage(ship) or {}
    # the expert data its next stages read, where this machine lacks it (the seed data waits for DAggerFM)
    progress = layout.out / system.name / "collect.json"
    progress.parent.mkdir(parents=True, exist_ok=True)
    progress.unlink(missing_ok=True)
    for name in data_needed(layout, recipe, [system]):
        if name != "seed":
            collect_store(layout, recipe, name, workers=threads, log=log, progress=progress)

    def keep(run_root: Path, name: str, epoch: int, total: int, to_ship: bool) -> None:
        """Every finished epoch goes to OUT/<name>/latest (`keep_latest` ships it on demand); every few, and the
        last, to the stage copy."""
        stage = {"system": system.name, "label": system.label, "stage": name, "epoch": epoch, "epochs": total,
                 "recipe": recipe.to_dict()}
        supervised_log = None
        if name == "dagger":  # from the supervised run, or the stage copy where that run is gone
            supervised_log = next((path for path in (sup_run / "log.jsonl", ship / "run" / SUPERVISED_LOG,
                                                     layout.latest(system) / "run" / SUPERVISED_LOG)
                                   if path.is_file()), None)
        publish(run_root, layout.latest(system), {**stage, "evaluated": False}, supervised_log)
        with ship_lock(ship):
            shipped = read_stage(ship)
            # shipped from another machine while this trained (evaluated or not: a longer recipe trains on past it)
            if stage_order(shipped) > stage_order(stage):
                log(f"{system.name}: {ship} holds a further stage ({describe_stage(shipped, ship)}): not replaced")
                superseded.append(name)
                return
            if not to_ship:
                return
            publish(run_root, ship, stage, supervised_log)
        where = f"{name} {'epoch' if name == 'supervised' else 'iteration'} {epoch} of {total}"
        log(f"{system.name}: kept {where} in {ship}")
        if commit and epoch == total:  # a stage's end; between, `keep_latest` commits before the work pauses
            git_commit([ship], f"table2: {system.label}, {where} (stage copy for resuming)", log)

    def catch_up(run_root: Path, name: str, total: int) -> bool:
        """Copy the finished run's last epoch to the stage copy where a kill came between the run's saved state and
        that copy (a restart trains no further, so `keep` is not called again); False if superseded meanwhile."""
        if stage_order(read_stage(ship)) < stage_order({"stage": name, "epoch": total}):
            keep(run_root, name, total, total, True)
        return not superseded

    # 1. supervised learning
    if stage.get("stage") == "supervised" and _state_epoch(sup_run) < stage["epoch"]:
        log(f"{system.name}: restoring supervised epoch {stage['epoch']} from {ship}")
        restore(ship, sup_run)
    in_dagger = stage.get("stage") == "dagger" or _state_epoch(dagger_run) >= 0
    # a finished supervised run (restored from its last stage copy, DAggerFM's run lost) reads no train data
    if not in_dagger and _state_epoch(sup_run) < recipe.epochs:
        def on_epoch(state) -> None:
            keep(sup_run, "supervised", state.epoch, recipe.epochs,
                 state.epoch % recipe.publish_every_epochs == 0 or state.epoch == recipe.epochs)

        train_supervised(sup_run, system.kind, sup_config, EpisodeStore(layout.data / "expert_train"),
                         EpisodeStore(layout.data / "expert_dev"), log=log, on_progress=on_progress,
                         on_epoch=on_epoch, stop_after=_at_epoch_end(stop_after, "supervised", superseded))
        if superseded or _state_epoch(sup_run) < recipe.epochs:
            return None
    if not in_dagger and not catch_up(sup_run, "supervised", recipe.epochs):
        return None

    # 2. DAggerFM
    if stage.get("stage") == "dagger" and _state_epoch(dagger_run) < stage["epoch"]:
        log(f"{system.name}: restoring DAggerFM iteration {stage['epoch']} from {ship}")
        restore(ship, dagger_run)
    if _state_epoch(dagger_run) < 0:  # a new DAggerFM run starts its dataset from the seed data
        collect_store(layout, recipe, "seed", workers=threads, log=log, progress=progress)
    # a resumed run reads its weights and Adam from its own state; `init` then only names the architecture, so the
    # stage copy serves when the supervised run folder is gone
    init = sup_run / "checkpoint" if (sup_run / "checkpoint" / "meta.json").is_file() else ship

    def on_iteration(state) -> None:
        keep(dagger_run, "dagger", state.epoch, recipe.iterations,
             state.epoch % recipe.publish_every_iterations == 0 or state.epoch == recipe.iterations)

    train_dagger(dagger_run, init, dagger_config, EpisodeStore(layout.data / "expert_seed"),
                 EpisodeStore(layout.data / "expert_dev"), env_ids=environments(recipe)["fresh"], log=log,
                 on_progress=on_progress, on_iteration=on_iteration,
                 stop_after=_at_epoch_end(stop_after, "dagger", superseded))
    if superseded or _state_epoch(dagger_run) < recipe.iterations or not catch_up(dagger_run, "dagger",
                                                                                   recipe.iterations):
        return None

    # 3. evaluation on dev
    evaluation = ship / "evaluation.json"
    if not evaluation.is_file() or not (read_stage(ship) or {}).get("evaluated"):
        if not evaluation.is_file():
            write_json(evaluation, evaluate_system(system, layout, recipe, threads, log, commit=commit))
        partial_path(ship, "dev").unlink(missing_ok=True)  # the commit below removes it from the repository too
        write_stage(ship, {**(read_stage(ship) or {}), "evaluated": True})
        s = json.loads(evaluation.read_text())["summary"]
        log(f"{system.name}: {s['success']:.1f} % success on {s['count']} dev environments")
        if commit:
            git_commit([ship], f"table2: {system.label}, evaluated on {s['count']} dev environments", log)

    # 4. Table 1's test environments, for the control and -J_plan, unless the control missed the gate (a recipe
    # extended for all six would make this evaluation stale)
    table1 = ship / EVALUATIONS["test"][1]
    if system.name in TABLE1 and not table1.is_file():
        def below_gate() -> bool:
            success = control_below_gate(layout, recipe)
            if success is not None:
                log(f"{system.name}: no Table 1 evaluation: the control flies {success:.1f} % on dev, below the "
                    f"recipe's gate of {recipe.control_gate:.0f} % (docs/training.md)")
            return success is not None

        results = None if below_gate() else evaluate_system(system, layout, recipe, threads, log, split="test",
                                                            commit=commit, stop=below_gate)
        if results is None:
            return json.loads(evaluation.read_text())
        write_json(table1, results)
        partial_path(ship, "test").unlink(missing_ok=True)
        s = results["summary"]
        log(f"{system.name}: {s['success']:.1f} % success on {s['count']} test environments (Table 1)")
        if commit:
            git_commit([ship], f"table2: {system.label}, evaluated on {s['count']} test environments (Table 1)", log)
    return json.loads(evaluation.read_text())


def _at_epoch_end(stop_after, stage: str, superseded: list[str]):
    """The training loops' `stop_after` (asked after every saved state): at an epoch's end, once the stage copy was
    found further on (`superseded`) or when `stop_after(stage, state)` says so."""
    return lambda state: state.batch == 0 and (bool(superseded) or (stop_after is not None and
                                                                   stop_after(stage, state)))


def evaluate_system(system: System, layout: Layout, recipe: Recipe, threads: int, log=print,
                    split: str = "dev", commit: bool = False, stop: Callable[[], bool] | None = None) -> dict | None:
    """Fly the finished system on the dev (or Table 1's test) environments with `gsmn eval`, record the maps,
    attribute each failure; a compact result. Flown EVAL_CHUNK environments at a time: each finished chunk's compact
    episodes are kept beside the stage copy (`partial_path`; committed by `keep_latest`), so a new machine flies only
    the rest; within a chunk, `gsmn eval --resume` keeps the finished episodes on this machine. None where `stop()`,
    asked before each chunk, says to stop (the chunks flown are kept)."""
    from gsmn.analysis.slices import episode_facts
    from gsmn.attribution import Heads, attribute_record, load_trace, trace_path
    from gsmn.evaluation import write_json
    from gsmn.model.checkpoint import load_checkpoint
    from gsmn.task.metrics import summarize
    from gsmn.world.spec import world_for_env

    ship = layout.shipped(system)
    folder = layout.out / system.name
    which, _, full_name, record_name = EVALUATIONS[split]
    record = folder / record_name
    ids = environments(recipe)[which]
    kept = kept_partial(ship, split, ids)
    episodes = {int(e["env_id"]): e for e in kept["episodes"]}
    config_dict = kept.get("config")
    if episodes:
        log(f"{system.name}: {len(episodes)} of {len(ids)} {split} environments kept in {partial_path(ship, split)}")
    key = stage_key(read_stage(ship))  # read once: the stage copy does not change while it is evaluated
    heads, tag = None, chunk_tag(key)
    for start in range(0, len(ids), EVAL_CHUNK):
        chunk = [i for i in ids[start:start + EVAL_CHUNK] if i not in episodes]
        if not chunk:
            continue
        if stop is not None and stop():
            return None
        # named by the stage copy and the environments, so a file of another copy or chunking is never reused
        full = folder / f"{Path(full_name).stem}.{tag}.{start}-{start + len(chunk)}.json"
        if not full.is_file():
            command = [sys.executable, "-m", "gsmn.cli", "eval", "--system", system.kind, "--checkpoint", str(ship),
                       "--env-ids", ",".join(map(str, chunk)), "--json", str(full), "--record", str(record),
                       "--workers", "1", "--threads", str(threads), "--preset", recipe.preset,
                       "--camera.shadow-method", recipe.shadow_method]
            if Path(str(full) + ".partial.jsonl").is_file():
                command.append("--resume")
            log(f"{system.name}: flying {len(chunk)} {split} environments ({len(episodes)} of {len(ids)} done)")
            subprocess.run(command, check=True)
        results = json.loads(full.read_text())
        if [int(e["env_id"]) for e in results["episodes"]] != chunk:
            raise ValueError(f"{full} holds other environments than {chunk}: remove it and start again")
        config_dict = results["config"]
        if heads is None:  # the first-person baselines keep no world maps: nothing to attribute
            model, *_ = load_checkpoint(ship)
            heads = Heads.of(model) if getattr(model.heads, "goal", None) is not None else False
        config = RunConfig.from_dict(config_dict)
        for ep in results["episodes"]:
            attribution = None  # every episode's, a success's too: its map readings (gsmn.analysis.slices)
            if heads and trace_path(record, int(ep["env_id"])).is_file():
                attribution = attribute_record(ep, load_trace(trace_path(record, int(ep["env_id"]))), heads, config)
            facts = episode_facts(ep, world_for_env(int(ep["env_id"]), config.world),
                                  attribution.to_dict() if attribution else None, config.task.success_radius)
            episodes[int(ep["env_id"])] = {k: v for k, v in ep.items() if k not in PER_STEP} | {
                "stage": attribution.stage if attribution else None, "facts": facts}
        if len(episodes) < len(ids):
            write_json(partial_path(ship, split), {
                "system": system.name, "split": split, "env_ids": ids, "stage": key,
                "config": config_dict, "episodes": [episodes[i] for i in ids if i in episodes]})
    ordered = [episodes[i] for i in ids]
    radius = RunConfig.from_dict(config_dict).task.success_radius
    return {"system": system.name, "label": system.label, "recipe": recipe.to_dict(), "split": split, "env_ids": ids,
            "summary": summarize(ordered, radius).to_dict(), "episodes": ordered}


PER_STEP = ("trajectory", "actions", "stop_probabilities", "member_stop_probabilities")  # not kept: the bulk


# -- the programme ----------------------------------------------------------------------------------------------
def done(layout: Layout, system: System, recipe: Recipe) -> bool:
    """Trained to this recipe's end and evaluated (on Table 1's test environments too, for TABLE1 systems, unless
    the control missed the gate): a finished stage copy, which holds no optimizer state and is never restored."""
    ship = layout.shipped(system)
    stage = read_stage(ship)
    if not (stage and stage.get("evaluated") and finished(stage, recipe) and (ship / "evaluation.json").is_file()):
        return False
    return (system.name not in TABLE1 or (ship / EVALUATIONS["test"][1]).is_file()
            or control_below_gate(layout, recipe) is not None)


def control_below_gate(layout: Layout, recipe: Recipe) -> float | None:
    """The control's dev success where it is evaluated, trained to this recipe's end and below its gate; else None."""
    ship = layout.shipped(SYSTEMS[0])
    stage = read_stage(ship) or {}
    if not (stage.get("evaluated") and finished(stage, recipe)):
        return None
    try:
        success = json.loads((ship / "evaluation.json").read_text())["summary"]["success"]
    except (OSError, ValueError, KeyError):
        return None
    return success if success < recipe.control_gate else None


def run_programme(layout: Layout, recipe: Recipe, recipe_name: str, systems: list[System], parallel: int = 2,
                  commit: bool = False, device: str = "cpu") -> int:
    """Every system's pipeline not yet done (`done`), `parallel` at a time, the machine's cores shared out among them
    (on two cores: one thread each side by side, else two), each in its own process logging to OUT/<name>/log.txt,
    with a progress bar per running system; training on `device`. Returns a shell status."""
    from tqdm import tqdm

    cores = len(os.sched_getaffinity(0))
    # each system collects the expert data it reads when it needs it (`collect_store`), on its share of the cores
    threads = max(1, cores // parallel)
    pending, running, failed = [s for s in systems if not done(layout, s, recipe)], {}, []
    bars: dict[str, Any] = {}
    gate_closed = False
    if SYSTEMS[0] in systems and SYSTEMS[0] not in pending:  # the control is done already: its gate holds at once
        gate_closed = control_below_gate(layout, recipe) is not None
        if gate_closed:
            tqdm.write(f"the control flies {control_below_gate(layout, recipe):.1f} % on dev, below the recipe's "
                       f"gate of {recipe.control_gate:.0f} %: no further system starts (docs/training.md)")
    try:
        while (pending and not gate_closed) or running:
            while pending and len(running) < parallel and not gate_closed:
                system = pending.pop(0)
                (layout.out / system.name).mkdir(parents=True, exist_ok=True)
                logfile = (layout.out / system.name / "log.txt").open("a")
                command = [sys.executable, "-m", "gsmn.cli", "experiment", "table2", "--out", str(layout.out),
                           "--ship", str(layout.ship), "--recipe", recipe_name, "--system", system.name,
                           "--threads", str(threads), "--device", device] + (["--git-commit"] if commit else [])
                running[system.name] = (subprocess.Popen(command, stdout=logfile, stderr=subprocess.STDOUT), logfile)
                bars[system.name] = tqdm(total=1, desc=system.name, position=len(bars), file=sys.stderr,
                                         dynamic_ncols=True, leave=True)
            for name, (process, logfile) in list(running.items()):
                if process.poll() is None:
                    continue
                logfile.close()
                del running[name]
                if process.returncode != 0:
                    failed.append(name)
                    tqdm.write(f"{name}: stopped with status {process.returncode}; see {layout.out / name / 'log.txt'}")
                if name == SYSTEMS[0].name and name not in failed:
                    success = control_below_gate(layout, recipe)
                    if success is not None:
                        gate_closed = True
                        tqdm.write(f"the control flies {success:.1f} % on dev, below the recipe's gate of "
                                   f"{recipe.control_gate:.0f} %: the ablations' drops would be noise, so no further "
                                   "system starts and no Table 1 evaluation either (docs/training.md)")
            for name, bar in bars.items():
                show_progress(bar, name, *describe(layout, BY_NAME[name], recipe))
            time.sleep(2)
    finally:
        for process, _ in running.values():  # stopped (Ctrl-C, SIGTERM): the children save and stop too
            process.terminate()
        for process, logfile in running.values():
            process.wait()
            logfile.close()
        for bar in bars.values():
            bar.close()
    if gate_closed or failed:
        return 1
    print(table_markdown(layout.ship))
    return 0


def show_progress(bar: Any, name: str, desc: str, done: int, total: int) -> None:
    """Move a system's tqdm bar to where its pipeline stands. A new stage (a new description) restarts the bar's
    clock, and what the stage had done before the bar saw it (a resumed evaluation) counts as its start, so the
    elapsed time, rate and ETA shown are the current stage's. A count that goes back (a stage restarted from its
    stage copy, after the bar read the stopped run's progress file) restarts the clock too."""
    label = f"{name}: {desc}"
    if label != bar.desc or done < bar.initial:
        bar.reset(total=max(total, 1))
        bar.set_description_str(label, refresh=False)
        bar.initial = done
    bar.total, bar.n = max(total, 1), done
    bar.refresh()


def describe(layout: Layout, system: System, recipe: Recipe) -> tuple[str, int, int]:
    """Where a system's pipeline stands, for its progress bar: (what, done, total)."""
    folder = layout.out / system.name
    try:
        c = json.loads((folder / "collect.json").read_text())
        return f"collecting {STORES[c['store']]}", int(c["done"]), int(c["total"])
    except (OSError, ValueError, KeyError):
        pass
    ship = layout.shipped(system)
    if (ship / "evaluation.json").is_file() and finished(read_stage(ship), recipe):
        if system.name not in TABLE1 or (ship / "table1.json").is_file():
            return "evaluated", 1, 1
        if control_below_gate(layout, recipe) is not None:
            return "evaluated on dev (the control is below the gate: no Table 1)", 1, 1
        return ("evaluating on test (Table 1)", min(_evaluation_done(layout, system, "test"), recipe.table1_envs),
                recipe.table1_envs)
    if kept_partial(ship, "dev")["episodes"] or list(folder.glob(f"evaluation_full.{chunk_tag(read_stage(ship))}.*")):
        return "evaluating on dev", min(_evaluation_done(layout, system, "dev"), recipe.eval_envs), recipe.eval_envs
    for stage in ("dagger", "supervised"):
        try:
            p = json.loads((folder / stage / "progress.json").read_text())
        except (OSError, ValueError):
            continue
        if "iteration" in p:
            where = f"DAggerFM iteration {p['iteration']}/{p['iterations']} {p.get('phase', '')}"
        else:
            where = f"supervised epoch {p.get('epoch')}/{p.get('epochs')} {p.get('phase', '')}"
        if p.get("phase") == "collect":
            return where, int(p.get("done", 0)), int(p.get("rollouts", 1))
        return where, int(p.get("batch", 0)), int(p.get("batches", 1))
    return "starting", 0, 1


def _evaluation_done(layout: Layout, system: System, split: str) -> int:
    """Episodes of an evaluation in progress: those kept beside the stage copy, and those of the chunk in flight."""
    ship = layout.shipped(system)
    kept = len(kept_partial(ship, split)["episodes"])
    stem, tag = Path(EVALUATIONS[split][2]).stem, chunk_tag(read_stage(ship))
    flying = 0
    for path in (layout.out / system.name).glob(f"{stem}.{tag}.*.json.partial.jsonl"):
        try:
            flying += max(0, len(path.read_text().splitlines()) - 1)  # a header line, then an episode a line
        except OSError:
            pass
    return kept + flying

