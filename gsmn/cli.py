"""The `gsmn` command line: one subcommand per job.

Config flags are generated from the dataclasses in gsmn.config: `--preset tiny` picks a preset and every
leaf field can be overridden by its dotted path, e.g. `--camera.pitch-deg 30 --world.seed 1`. Installed packages
add subcommands through the entry-point group `gsmn.commands` (the dashboard's `gsmn serve`, from app.cli).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

from gsmn import executor
from gsmn.config import PRESETS, ConfigError, RunConfig, leaf_fields, preset, with_overrides


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("configuration (see gsmn/config.py)")
    group.add_argument("--preset", choices=PRESETS, default=None, help="named preset (default: paper)")
    group.add_argument("--config", default=None, metavar="FILE",
                       help="start from this saved RunConfig JSON (e.g. a run folder's config.json) instead of a "
                            "preset; the flags below still override it")
    for path, hint, f in leaf_fields(RunConfig):
        flag = "--" + path.replace("_", "-")
        name = getattr(hint, "__name__", str(hint))
        group.add_argument(flag, dest="cfg:" + path, metavar=name.upper(), default=None,
                           help=f"{f.metadata.get('help', '')} (default: {f.default})".replace("%", "%%"))


def config_from_args(args: argparse.Namespace) -> RunConfig:
    """The preset (or the --config file), with the flags given applied over it."""
    overrides = {k[4:]: v for k, v in vars(args).items() if k.startswith("cfg:") and v is not None}
    if args.config is not None and args.preset is not None:
        raise ConfigError("give --preset or --config, not both")
    if args.config is not None:
        path = Path(args.config)
        try:
            base = RunConfig.from_dict(json.loads(path.read_text()))
        except OSError as e:
            raise ConfigError(f"cannot read --config {path}: {e.strerror or e}") from e
        except (ValueError, TypeError) as e:  # ConfigError is a ValueError: its message names the field
            raise ConfigError(f"--config {path} is not a RunConfig JSON file: {e}") from e
    else:
        base = preset(args.preset or "paper")
    return with_overrides(base, overrides)


# -- gsmn world -------------------------------------------------------------------------------------
def cmd_world(args: argparse.Namespace) -> int:
    from gsmn.world.spec import world_for_env

    config = config_from_args(args)
    world = world_for_env(args.env_id, config.world)
    if args.json or not args.out:
        print(json.dumps(world_summary(world), indent=1))
    if args.out:
        paths = write_world_preview(world, config, Path(args.out))
        for p in paths:
            print(f"wrote {p}", file=sys.stderr)
    return 0


def cmd_understand(args: argparse.Namespace) -> int:
    """Free text read in an environment's world as the template the model flies (gsmn.task.understand): status 0
    and the template, or status 2 and why not, with the nearest instructions this world allows."""
    from gsmn.task.understand import understand
    from gsmn.world.spec import world_for_env

    u = understand(" ".join(args.text), world_for_env(args.env_id, config_from_args(args).world))
    print(json.dumps(u.to_dict(), indent=1) if args.json else u.message())
    return 0 if u.ok else 2


def world_summary(world) -> dict:
    """The WorldSpec as the CLI prints it: landmarks with name, noun phrase, x, y, radius; start pose."""
    return {
        "env_id": world.env_id,
        "split": world.split,
        "field_size": world.field_size,
        "landmarks": [{"name": lm.model, "noun_phrase": lm.noun_phrase, "class_id": lm.class_id,
                       "x": round(lm.x, 4), "y": round(lm.y, 4), "radius": round(lm.radius, 4),
                       "yaw": round(lm.yaw, 4), "scale": round(lm.scale, 4)} for lm in world.landmarks],
        "lakes": [{"x": round(lk.x, 4), "y": round(lk.y, 4), "radius_x": round(lk.radius_x, 4),
                   "radius_y": round(lk.radius_y, 4), "yaw": round(lk.yaw, 4)} for lk in world.lakes],
        "start": {"corner": world.start_corner, "x": world.start_x, "y": world.start_y,
                  "yaw": round(world.start_yaw, 6)},
    }


def write_world_preview(world, config: RunConfig, out: Path) -> list[Path]:
    """The first camera image and an annotated top-down view of a world, as PNGs."""
    from PIL import Image, ImageDraw

    from gsmn.world.sim import Simulator, topdown_extent, topdown_pixel

    out.mkdir(parents=True, exist_ok=True)
    sim = Simulator(world, config)
    try:
        fpv = Image.fromarray(sim.render())
        size = 768
        top = Image.fromarray(sim.render_topdown(size))
    finally:
        sim.close()
    draw = ImageDraw.Draw(top)
    for lm in world.landmarks:
        u, v = topdown_pixel(world, lm.x, lm.y, size)
        r = lm.radius / topdown_extent(world) * size
        draw.ellipse([u - r, v - r, u + r, v + r], outline=(255, 255, 255))
        draw.text((u - r, v + r + 2), lm.noun_phrase, fill=(255, 255, 255), stroke_width=2, stroke_fill=(0, 0, 0))
    su, sv = topdown_pixel(world, world.start_x, world.start_y, size)
    draw.text((min(su, size - 60), min(sv, size - 16)), "start", fill=(255, 255, 0), stroke_width=2,
              stroke_fill=(0, 0, 0))
    paths = [out / f"env_{world.env_id}_camera.png", out / f"env_{world.env_id}_topdown.png"]
    fpv.save(paths[0])
    top.save(paths[1])
    return paths


# -- gsmn eval / fit-avg-forward --------------------------------------------------------------------
def _progress(total: int, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="episode", file=sys.stderr, dynamic_ncols=True)


class _TrainingBars:
    """Progress bars for `gsmn train`: one per epoch (or DAgger iteration) and phase, from the progress dicts
    the training loops report."""

    def __init__(self):
        self.bar, self.key = None, None

    def __call__(self, p: dict) -> None:
        from tqdm import tqdm

        phase = p.get("phase")
        if phase not in ("train", "collect"):
            return
        if "iteration" in p:
            where = f"iteration {p['iteration']}/{p['iterations']}"
        else:
            where = f"epoch {p.get('epoch')}/{p.get('epochs')}"
        key = (phase, where)
        total, done = (p["batches"], p["batch"]) if phase == "train" else (p["rollouts"], p["done"])
        if key != self.key:
            self.close()
            unit = "batch" if phase == "train" else "rollout"
            what = "training" if phase == "train" else f"rollouts (beta {p.get('beta')})"
            desc = f"{where} {what}"
            self.bar = tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True)
            self.key = key
        self.bar.n = done
        if phase == "train" and p.get("loss") is not None:
            self.bar.set_postfix(loss=f"{p['loss']:.3f}", refresh=False)
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        self.bar, self.key = None, None


def cmd_eval(args: argparse.Namespace) -> int:
    import time

    from gsmn.evaluation import (
        TABLE_HEADER,
        PartialResults,
        ProgressLog,
        checkpoint_fingerprint,
        env_ids_for,
        evaluate,
        results_dict,
        table_row,
        write_json,
    )
    from gsmn.task.metrics import summarize

    config = config_from_args(args)
    executor_options = executor.options_from_args(args)
    env_ids = env_ids_for(args.split, args.episodes, args.env_ids)
    intervention = None
    if args.intervene:
        from gsmn.analysis.intervention import intervention_from_flag

        intervention = intervention_from_flag(args.intervene)
    if args.resume and not args.json:
        raise ValueError("--resume continues the evaluation that writes --json F (from F.partial.jsonl): give --json")
    partial, done = None, []
    if args.json:
        partial = PartialResults(args.json)
        header = {"system": args.system, "env_ids": list(env_ids),
                  "checkpoint": checkpoint_fingerprint(args.system, args.checkpoint),
                  "mirror_ensemble": args.mirror_ensemble,
                  "ensemble_with": [checkpoint_fingerprint(args.system, c) for c in args.ensemble_with],
                  "config": config.to_dict(), **({"intervention": args.intervene} if args.intervene else {})}
        done = partial.open(header, args.resume)
        if done:
            print(f"resuming: {len(done)} of {len(env_ids)} episodes kept in {partial.path}", file=sys.stderr)
    if args.threads is not None:
        from gsmn.model.runtime import set_torch_threads

        set_torch_threads(args.threads)
    progress = (ProgressLog(Path(args.progress), len(env_ids), config.task.success_radius) if args.progress
                else None)
    if progress is not None:
        for record in done:
            progress.write(record)
    done_ids = {r.env_id for r in done}
    t0 = time.perf_counter()
    with _progress(len(env_ids), args.system) as bar:
        bar.update(len(done))

        def on_episode(record) -> None:
            bar.update(1)
            if partial is not None:
                partial.append(record)
            if progress is not None:
                progress.write(record)

        flown = evaluate(args.system, [e for e in env_ids if e not in done_ids], config, args.checkpoint,
                         args.workers, on_episode=on_episode, record_dir=args.record,
                         mirror_ensemble=args.mirror_ensemble, ensemble_with=args.ensemble_with,
                         executor_options=executor_options, intervention=intervention)
    seconds = time.perf_counter() - t0
    by_id = {r.env_id: r for r in done + flown}
    records = [by_id[e] for e in env_ids]
    summary = summarize(records, config.task.success_radius)
    print(TABLE_HEADER)
    print(table_row(args.system, summary))
    pruned = summary.pruned.count if summary.pruned else 0
    print(f"{len(records)} episodes ({pruned} unambiguous); {len(flown)} flown in {seconds:.0f} s with "
          f"{args.workers} worker(s): {60 * len(flown) / max(seconds, 1e-9):.1f} episodes/min")
    if args.json:
        results = results_dict(args.system, args.checkpoint, records, config, seconds, args.workers,
                               args.mirror_ensemble, args.ensemble_with)
        if intervention is not None:
            results["intervention"] = intervention.to_dict()
        write_json(Path(args.json), results)
        partial.remove()
        print(f"wrote {args.json}", file=sys.stderr)
    return 0


def cmd_fit_avg_forward(args: argparse.Namespace) -> int:
    from gsmn.evaluation import AVG_FORWARD_PATH, evaluate
    from gsmn.task.baselines import fit_avg_forward
    from gsmn.world.spec import split_env_ids

    config = config_from_args(args)
    env_ids = split_env_ids("train", args.episodes)
    with _progress(len(env_ids), "oracle on train") as bar:
        records = evaluate("oracle", env_ids, config, workers=args.workers, on_episode=lambda r: bar.update(1))
    average = fit_avg_forward(records)
    out = Path(args.out) if args.out else AVG_FORWARD_PATH
    average.save(out)
    print(f"avg-forward: v = {average.forward_velocity:.3f} m/s, omega = {average.yaw_rate:.4f} rad/s for "
          f"{average.steps} steps (from {average.episodes} expert episodes on train) -> {out}")
    return 0


# -- gsmn collect ----------------------------------------------------------------------------------
def cmd_collect(args: argparse.Namespace) -> int:
    from gsmn.evaluation import env_ids_for
    from gsmn.training.collect import collect_expert, episode_key
    from gsmn.training.store import EpisodeStore

    config = config_from_args(args)
    env_ids = env_ids_for(args.split, args.episodes, args.env_ids)
    store = EpisodeStore(args.out)
    before = len(store)
    frames = []
    with _progress(len(env_ids), "expert episodes") as bar:
        bar.update(sum(1 for e in env_ids if episode_key(e) in store))
        collect_expert(store, env_ids, config, workers=args.workers,
                       on_episode=lambda env_id, n: (frames.append(n), bar.update(1)),
                       executor_options=executor.options_from_args(args))
    print(f"{args.out}: {len(store)} episodes ({len(store) - before} new, {sum(frames)} new frames)")
    return 0


INIT_OPTIMIZER_HELP = ("also start Adam from the optimizer state saved in the --init checkpoint (its "
                       "optimizer.safetensors), to go on training as if the earlier run had not stopped; with this "
                       "run's learning rate")


# -- gsmn train -------------------------------------------------------------------------------------
def cmd_train_supervised(args: argparse.Namespace) -> int:
    from gsmn.model.runtime import keep_freed_memory
    from gsmn.training import distributed
    from gsmn.training.store import EpisodeStore
    from gsmn.training.supervised import train_supervised

    keep_freed_memory()  # process-wide allocator setting: about 1.35x training throughput (docs/model.md)
    config = config_from_args(args)
    for name in ("data", "dev"):
        path = getattr(args, name)
        if path and not Path(path).is_dir():
            raise FileNotFoundError(f"--{name} {path} does not exist; make it with `gsmn collect --out {path}`")
    bars, clean = _TrainingBars(), False
    try:
        checkpoint = train_supervised(Path(args.run), args.kind, config, EpisodeStore(args.data),
                                      EpisodeStore(args.dev) if args.dev else None,
                                      init=Path(args.init) if args.init else None, log=_above(bars),
                                      on_progress=bars, init_optimizer=args.init_optimizer)
        clean = True
    finally:
        bars.close()
        distributed.shutdown(clean)  # under torchrun: leave the process group before exiting
    print(f"checkpoint: {checkpoint}")
    return 0


def cmd_train_dagger(args: argparse.Namespace) -> int:
    from gsmn.model.runtime import keep_freed_memory
    from gsmn.training import distributed
    from gsmn.training.dagger import train_dagger
    from gsmn.training.store import EpisodeStore

    keep_freed_memory()
    config = config_from_args(args)
    for name in ("data", "dev", "init"):
        path = getattr(args, name)
        if path and not Path(path).is_dir():
            raise FileNotFoundError(f"--{name} {path} does not exist")
    env_ids = None
    if args.env_ids:
        from gsmn.evaluation import parse_env_ids

        env_ids = parse_env_ids(args.env_ids)
    bars, clean = _TrainingBars(), False
    try:
        checkpoint = train_dagger(Path(args.run), Path(args.init), config, EpisodeStore(args.data),
                                  EpisodeStore(args.dev) if args.dev else None, env_ids=env_ids, log=_above(bars),
                                  on_progress=bars, init_optimizer=args.init_optimizer,
                                  executor_options=executor.options_from_args(args))
        clean = True
    finally:
        bars.close()
        distributed.shutdown(clean)  # under torchrun: leave the process group before exiting
    print(f"checkpoint: {checkpoint}")
    return 0


def _above(bars: _TrainingBars):
    """A logger that prints the epoch summary as its own line, below the finished bar."""

    def log(line: str) -> None:
        bars.close()
        print(line, flush=True)

    return log


# -- gsmn average / keep-iterations -----------------------------------------------------------------
def cmd_average(args: argparse.Namespace) -> int:
    from gsmn.model.checkpoint import average_checkpoints

    out = average_checkpoints(args.checkpoints, args.out)
    print(f"{out}: the mean of {len(args.checkpoints)} checkpoints' weights")
    return 0


def cmd_keep_iterations(args: argparse.Namespace) -> int:
    import time

    from gsmn.model.checkpoint import keep_iteration

    try:
        while True:
            kept = keep_iteration(args.run)
            if kept is not None:
                print(time.strftime("%H:%M:%S"), "kept", kept, flush=True)
            time.sleep(args.every)
    except KeyboardInterrupt:
        return 0


# -- gsmn attribute / analyze -----------------------------------------------------------------------
def _read_results(path: str) -> dict:
    return json.loads(Path(path).read_text())


def cmd_attribute(args: argparse.Namespace) -> int:
    from gsmn.analysis.failures import print_report

    print_report(_read_results(args.results), Path(args.recordings), Path(args.checkpoint) if args.checkpoint else None)
    return 0


def cmd_analyze_table1(args: argparse.Namespace) -> int:
    from gsmn.analysis.table1 import table

    labels = dict(item.split("=", 1) for item in args.label)
    print(table([_read_results(f) for f in args.files], labels, args.files))
    return 0


def cmd_analyze_regions(args: argparse.Namespace) -> int:
    from gsmn.analysis.regions import region_table

    evaluations = [spec.partition("=")[::2] for spec in args.evaluations]
    for spec, (_, path) in zip(args.evaluations, evaluations, strict=True):
        if not path:
            raise ValueError(f"expected NAME=PATH, got {spec!r}")
    print(region_table([(name, Path(path)) for name, path in evaluations], args.radius))
    return 0


def cmd_analyze_stop_threshold(args: argparse.Namespace) -> int:
    from gsmn.analysis.stop_threshold import rescore

    write = (float(args.write[0]), Path(args.write[1])) if args.write else None
    print(rescore(Path(args.results), Path(args.record) if args.record else None, args.taus, args.radius, write))
    return 0


def cmd_analyze_compare(args: argparse.Namespace) -> int:
    from gsmn.analysis.compare import compare_report

    print(compare_report(args.before, args.after, args.records_before, args.records_after, args.name, args.png))
    return 0


def cmd_analyze_slices(args: argparse.Namespace) -> int:
    from gsmn.analysis import slices
    from gsmn.evaluation import write_json

    def rows_of(path: str, record: str | None) -> list[dict]:
        results = _read_results(path)
        rows = slices.with_facts(results, Path(record) if record else None,
                                 Path(args.checkpoint) if args.checkpoint and path == args.results else None,
                                 log=lambda line: print(f"gsmn analyze slices: {line}", file=sys.stderr))
        if (args.keep_facts or args.write_compact) and path == args.results:
            by_env = {r["env_id"]: r for r in rows}
            for episode in results["episodes"]:
                episode["facts"] = by_env[int(episode["env_id"])]["facts"]
                if episode.get("stage") is None and not episode["success"]:
                    episode["stage"] = by_env[int(episode["env_id"])]["stage"]
            if args.keep_facts:  # kept in the file: the next reading computes nothing
                write_json(Path(path), results)
            if args.write_compact:  # as the Table 2 programme ships its evaluations: no per-step fields
                from gsmn.experiments.programme import PER_STEP

                write_json(Path(args.write_compact), {**results, "episodes": [
                    {k: v for k, v in e.items() if k not in PER_STEP} for e in results["episodes"]]})
        return rows

    other = rows_of(args.versus, args.versus_record) if args.versus else None
    analysis = slices.analyze(rows_of(args.results, args.record), other)
    if other is not None and analysis["versus_summary"]["n"] == 0:
        raise ValueError(f"{args.results} and {args.versus} share no environment: nothing to compare")
    if args.json:
        write_json(Path(args.json), analysis)
    if args.markdown or not args.json:
        print(slices.markdown(analysis, args.name or Path(args.results).parent.name or args.results,
                              args.versus_name or (Path(args.versus).parent.name if args.versus else "")))
    return 0


def cmd_analyze_rescue(args: argparse.Namespace) -> int:
    from gsmn.analysis import rescue
    from gsmn.evaluation import checkpoint_path, write_json

    results = _read_results(args.results)
    config = config_from_args(args)
    folder = Path(args.checkpoint) if args.checkpoint else checkpoint_path("gsmn", results.get("checkpoint"))
    failures = rescue.failures_of(results)
    if not failures:
        raise ValueError(f"{args.results} has no failure to rescue")
    out = Path(args.out)
    flags = args.interventions
    with _progress(len(failures) * len(flags), "rescue") as bar:
        stages, replayed = rescue.stages_of(failures, folder, config, args.record, args.workers)
        flown = {flag: rescue.fly_intervention(flag, sorted(stages), folder, config, out, args.workers,
                                               on_episode=lambda r: bar.update(1)) for flag in flags}
    table = rescue.rescue_table(stages, {f: [(r.env_id, r.success) for r in records] for f, records in flown.items()},
                                replayed)
    table.update(evaluation=args.results, checkpoint=str(folder))
    write_json(out / "rescue.json", table)
    if args.write_compact:  # as the shipped evaluations are kept: no per-step fields
        from gsmn.experiments.programme import PER_STEP

        for flag in flags:
            results = json.loads((out / f"{flag}.json").read_text())
            results["episodes"] = [{k: v for k, v in e.items() if k not in PER_STEP} for e in results["episodes"]]
            write_json(Path(args.write_compact) / f"{flag}.json", results)
    print(rescue.rescue_markdown(table))
    return 0


def cmd_map_codes(args: argparse.Namespace) -> int:
    from gsmn.analysis import rescue
    from gsmn.evaluation import env_ids_for

    config = config_from_args(args)
    env_ids = env_ids_for("dev" if args.env_ids is None else None, args.episodes, args.env_ids)
    with _progress(len(env_ids), "calibration flights") as bar:
        codes = rescue.calibrate(args.checkpoint, env_ids, config, args.workers, on_episode=lambda r: bar.update(1))
    path = rescue.save_codes(args.checkpoint, codes)
    m = codes.meta
    print(f"wrote {path}: {m['classes_seen']} of {len(codes.semantic_known)} landmark classes seen, "
          f"{m['successes']} of {m['episodes']} flights succeeded (relevance and goal codes from "
          f"{m['relevance_goal_from']})")
    return 0


def cmd_analyze_dagger(args: argparse.Namespace) -> int:
    from gsmn.analysis.dagger import dagger_table

    print(dagger_table(args.runs, args.first, args.dataset))
    return 0


# -- entry point ------------------------------------------------------------------------------------
COMMAND_GROUP = "gsmn.commands"


def add_installed_commands(sub: argparse._SubParsersAction) -> None:
    """Subcommands that installed packages declare in the entry-point group `gsmn.commands`, each a
    `register(subparsers)` that adds its parser. The dashboard's `gsmn serve` comes this way (app.cli), so the
    library never imports the app."""
    from importlib.metadata import entry_points

    for entry in sorted(entry_points(group=COMMAND_GROUP), key=lambda e: e.name):
        entry.load()(sub)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gsmn", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("world", help="print a world as JSON and/or write its first camera image and top-down view")
    p.add_argument("--env-id", type=int, required=True, help="environment id (id %% 100: 0-69 train, 70-84 test, "
                   "85-99 dev)")
    p.add_argument("--json", action="store_true", help="print the WorldSpec as JSON (default when no --out)")
    p.add_argument("--out", type=str, default=None, help="folder to write the PNGs into")
    add_config_arguments(p)
    p.set_defaults(func=cmd_world)

    p = sub.add_parser("understand", help="read a typed instruction in an environment's world as the template the "
                       "model flies, or say why not (the page and the API read typed text the same way)")
    p.add_argument("--env-id", type=int, required=True, help="environment id (its world's landmarks)")
    p.add_argument("--json", action="store_true", help="print everything understood as JSON")
    p.add_argument("text", nargs="+", help='e.g. "fly behind the red phone booth"')
    add_config_arguments(p)
    p.set_defaults(func=cmd_understand)

    p = sub.add_parser("eval", help="fly a system on environments and print its Table 1 row")
    p.add_argument("--system", required=True,
                   help="gsmn, gsmn-no-plan, gs-fpv, gs-fpv-mem (checkpoints/SYSTEM unless --checkpoint; gsmn-no-plan: "
                        "checkpoints/table2/no-plan), oracle, avg-forward, random-point, random-landmark")
    p.add_argument("--checkpoint", default=None, help="the system's checkpoint (avg-forward: its JSON)")
    p.add_argument("--split", choices=("train", "test", "dev"), default=None, help="evaluate on this split")
    p.add_argument("--episodes", type=int, default=None, help="how many environments of the split (default 750)")
    p.add_argument("--env-ids", default=None, help="'A:B' or '3,17,42' instead of a split")
    p.add_argument("--json", default=None, help="write per-episode records and the summary here")
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    p.add_argument("--threads", type=int, default=None, help="torch threads in this process (default: torch's own)")
    p.add_argument("--record", default=None, help="folder for each episode's final maps and per-step readings "
                   "(GSMN only), for failure attribution")
    p.add_argument("--progress", default=None, help="append one JSON line per finished episode to this file")
    p.add_argument("--resume", action="store_true",
                   help="continue an evaluation that was stopped before writing --json F: the episodes it finished "
                        "are kept in F.partial.jsonl, and only the rest are flown (the same system, environments, "
                        "checkpoint and settings only)")
    p.add_argument("--mirror-ensemble", action="store_true",
                   help="fly a learned model as a test-time mirror ensemble: it also flies the mirror image of each "
                        "step and the two actions are averaged (twice the compute; not in the paper)")
    p.add_argument("--ensemble-with", default=[], type=lambda s: [c for c in s.split(",") if c], metavar="CKPT,...",
                   help="more checkpoints of the same learned system to fly beside --checkpoint as a test-time "
                        "ensemble, their actions averaged (with --mirror-ensemble each also flies the mirror image; "
                        "not in the paper)")
    p.add_argument("--intervene", default=None, choices=("truth-semantic", "truth-relevance", "truth-goal"),
                   help="fly a GSMN with a map intervention from the first step: the true semantic map (perfect "
                        "perception), relevance map (perfect grounding) or goal map (perfect goal), in the model's "
                        "own coding (needs the checkpoint's map codes: `gsmn map-codes`; docs/model.md)")
    executor.add_arguments(p)
    add_config_arguments(p)
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("map-codes", help="derive a GSMN checkpoint's map codes (its own coding of each kind of "
                       "cell, for map interventions) from calibration flights on dev environments")
    p.add_argument("--checkpoint", required=True, help="the GSMN checkpoint folder (map_codes.safetensors goes there)")
    p.add_argument("--episodes", type=int, default=40, help="dev environments to fly (default 40)")
    p.add_argument("--env-ids", default=None, help="'A:B' or '3,17,42' instead of the first dev environments")
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    add_config_arguments(p)
    p.set_defaults(func=cmd_map_codes)

    p = sub.add_parser("fit-avg-forward", help="measure the avg-forward baseline from expert episodes on train")
    p.add_argument("--episodes", type=int, default=500, help="expert episodes to average over")
    p.add_argument("--workers", type=int, default=2, help="parallel worker processes")
    p.add_argument("--out", default=None, help="where to write (default checkpoints/avg_forward.json)")
    add_config_arguments(p)
    p.set_defaults(func=cmd_fit_avg_forward)

    p = sub.add_parser("collect", help="record expert episodes (images, poses, labels) into an episode store")
    p.add_argument("--out", required=True, help="store folder; episodes already there are skipped (resumable)")
    p.add_argument("--split", choices=("train", "test", "dev"), default="train")
    p.add_argument("--episodes", type=int, default=None, help="how many environments of the split (default 750)")
    p.add_argument("--env-ids", default=None, help="'A:B' or '3,17,42' instead of a split")
    p.add_argument("--workers", type=int, default=2, help="parallel worker processes")
    executor.add_arguments(p)
    add_config_arguments(p)
    p.set_defaults(func=cmd_collect)

    p = sub.add_parser("train", help="train a model: supervised on expert data, or DAggerFM")
    train_sub = p.add_subparsers(dest="mode", required=True)
    t = train_sub.add_parser("supervised", help="supervised learning on an episode store, resumable")
    t.add_argument("--data", required=True, help="episode store of expert training data (gsmn collect)")
    t.add_argument("--dev", default=None, help="episode store validated on after every epoch")
    t.add_argument("--run", "--run-dir", dest="run", required=True, help="run folder: config, log.jsonl, state/, "
                   "checkpoint/; an existing run resumes where it stopped (--run-dir under torchrun, which would "
                   "take --run for its own --run-path)")
    t.add_argument("--kind", default="gsmn", help="gsmn, gsmn-no-plan, gs-fpv, gs-fpv-mem")
    t.add_argument("--init", default=None, help="start from this checkpoint's weights")
    t.add_argument("--init-optimizer", action="store_true", help=INIT_OPTIMIZER_HELP)
    add_config_arguments(t)
    t.set_defaults(func=cmd_train_supervised)
    t = train_sub.add_parser("dagger", help="DAggerFM from a supervised checkpoint (paper Algorithm 1), resumable")
    t.add_argument("--init", required=True, help="the supervised checkpoint to start from (pi_1)")
    t.add_argument("--data", required=True, help="the expert episode store the initial dataset is sampled from")
    t.add_argument("--dev", default=None, help="episode store validated on after every iteration")
    t.add_argument("--run", "--run-dir", dest="run", required=True,
                   help="run folder (holds the dataset of M rollouts); resumes (--run-dir under torchrun)")
    t.add_argument("--env-ids", default=None, help="environments for rollouts (default: those of --data)")
    t.add_argument("--init-optimizer", action="store_true", help=INIT_OPTIMIZER_HELP)
    executor.add_arguments(t)
    add_config_arguments(t)
    t.set_defaults(func=cmd_train_dagger)

    p = sub.add_parser("experiment", help="run a whole experiment programme of the paper, resumable")
    from gsmn.experiments import table2

    table2.add_parser(p.add_subparsers(dest="experiment", required=True))

    p = sub.add_parser("average", help="average the weights of checkpoints of one model (e.g. several DAggerFM "
                       "iterations of one run) into a new checkpoint")
    p.add_argument("checkpoints", nargs="+", help="checkpoint folders of one model")
    p.add_argument("--out", required=True, help="the averaged checkpoint's folder")
    p.set_defaults(func=cmd_average)

    p = sub.add_parser("keep-iterations", help="beside `gsmn train ... --run RUN`: copy the run's checkpoint to "
                       "RUN_itN after every epoch or DAggerFM iteration N (without the Adam state), for "
                       "`gsmn average`; runs until stopped")
    p.add_argument("run", type=Path, help="the run folder of `gsmn train ... --run`")
    p.add_argument("--every", type=float, default=10.0, help="seconds between looks at the run's checkpoint")
    p.set_defaults(func=cmd_keep_iterations)

    p = sub.add_parser("attribute", help="failure attribution over an evaluation: each failed episode traced to the "
                       "first stage the model got wrong, and the counts")
    p.add_argument("results", help="gsmn eval --json output")
    p.add_argument("recordings", help="the same evaluation's --record folder")
    p.add_argument("--checkpoint", default=None, help="the model whose heads read the recorded maps (default: the "
                   "one the evaluation names, or checkpoints/gsmn)")
    p.set_defaults(func=cmd_attribute)

    p = sub.add_parser("analyze", help="tables from evaluations and training runs (markdown)")
    analyze = p.add_subparsers(dest="analysis", required=True)
    a = analyze.add_parser("table1", help="the paper's Table 1 beside ours, a row per evaluation (of the same "
                           "environments)")
    a.add_argument("files", nargs="+", help="gsmn eval --json outputs, one row each, in order")
    a.add_argument("--label", action="append", default=[], metavar="SYSTEM_OR_FILE=TEXT",
                   help="the row name for a system or for one file (e.g. gsmn='GSMN (20 epochs)')")
    a.set_defaults(func=cmd_analyze_table1)
    a = analyze.add_parser("regions", help="navigation against stopping: episodes that entered the success region, "
                           "and what they did there")
    a.add_argument("evaluations", nargs="+", metavar="NAME=EVAL_JSON", help="gsmn eval --json files, each named")
    a.add_argument("--radius", type=float, default=6.0, help="the success radius (m)")
    a.set_defaults(func=cmd_analyze_regions)
    a = analyze.add_parser("stop-threshold", help="an evaluation re-scored offline at lower STOP thresholds")
    a.add_argument("results", help="a `gsmn eval --json` file (a plain network or an ensemble with its P(stop))")
    a.add_argument("record", nargs="?", help="its --record folder (only for a file without stop_probabilities)")
    a.add_argument("--taus", type=float, nargs="+", default=None,
                   help="thresholds to score at (default: 0.5 down to 0.1 in steps of 0.05)")
    a.add_argument("--radius", type=float, default=None, help="default: the evaluation's own success radius")
    a.add_argument("--write", nargs=2, metavar=("TAU", "OUT"), help="write the evaluation as flown at TAU")
    a.set_defaults(func=cmd_analyze_stop_threshold)
    a = analyze.add_parser("compare", help="before/after of two checkpoints on the same environments")
    a.add_argument("--before", type=Path, nargs="+", required=True, help="gsmn eval --json files (merged)")
    a.add_argument("--after", type=Path, nargs="+", required=True, help="gsmn eval --json files (merged)")
    a.add_argument("--records-before", type=Path, default=None, help="the before evaluation's --record folder")
    a.add_argument("--records-after", type=Path, default=None, help="the after evaluation's --record folder")
    a.add_argument("--name", default="episodes", help="what the episodes are, for the table")
    a.add_argument("--png", type=Path, default=None, help="also draw the before/after figure here (matplotlib)")
    a.set_defaults(func=cmd_analyze_compare)
    a = analyze.add_parser("slices", help="an evaluation by slices (landmark, side, stage, map readings...), its "
                           "confusion matrices, and against another evaluation of the same environments slice by slice")
    a.add_argument("results", help="a gsmn eval --json file or a compact evaluation (checkpoints/table2/*/*.json)")
    a.add_argument("--record", default=None, help="its --record folder: the map readings (grounded landmark, goal "
                   "peak, the step it went wrong) for episodes that do not keep them")
    a.add_argument("--checkpoint", default=None, help="the model whose heads read --record (default: the one the "
                   "evaluation names)")
    a.add_argument("--versus", default=None, metavar="OTHER", help="another evaluation of the same environments: "
                   "fixed and broken episodes per slice, with a sign test")
    a.add_argument("--versus-record", default=None, help="OTHER's --record folder")
    a.add_argument("--json", default=None, metavar="OUT", help="write the analysis as JSON here")
    a.add_argument("--markdown", action="store_true", help="print the markdown tables (the default without --json)")
    a.add_argument("--name", default=None, help="what to call the evaluation (default: its folder's name)")
    a.add_argument("--versus-name", default=None, help="what to call OTHER (default: its folder's name)")
    a.add_argument("--keep-facts", action="store_true", help="write each episode's facts into RESULTS, so that a "
                   "later reading computes nothing")
    a.add_argument("--write-compact", default=None, metavar="OUT", help="write RESULTS with its facts and stages "
                   "and without the per-step fields (trajectories, actions), as the shipped evaluations are kept")
    a.set_defaults(func=cmd_analyze_slices)
    a = analyze.add_parser("rescue", help="how many of an evaluation's failures each truth map intervention saves, "
                           "per attributed stage (a causal check of failure attribution; docs/results.md)")
    a.add_argument("results", help="a `gsmn eval --json` file or a compact evaluation (its failures are flown again)")
    a.add_argument("--checkpoint", default=None, help="the GSMN checkpoint (default: the one the evaluation names)")
    a.add_argument("--record", default=None, help="the evaluation's --record folder, for the failures' stages "
                   "(otherwise each failure is flown once more without intervention, recording its maps)")
    a.add_argument("--interventions", default=list(("truth-semantic", "truth-relevance", "truth-goal")),
                   type=lambda s: [f for f in s.split(",") if f], metavar="FLAG,...",
                   help="which (default: truth-semantic,truth-relevance,truth-goal)")
    a.add_argument("--out", required=True, help="folder for each intervention's flights (a stopped run resumes) "
                   "and rescue.json")
    a.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    a.add_argument("--write-compact", default=None, metavar="DIR", help="also write each intervention's flights "
                   "there without their per-step fields (as checkpoints/gsmn/rescue/ ships them for the dashboard)")
    add_config_arguments(a)
    a.set_defaults(func=cmd_analyze_rescue)
    a = analyze.add_parser("dagger", help="DAggerFM runs side by side, an iteration a row")
    a.add_argument("runs", nargs="+", type=Path, help="DAggerFM run folders")
    a.add_argument("--first", type=int, default=1, help="first iteration to print")
    a.add_argument("--dataset", action="store_true", help="also summarise each run's dataset")
    a.set_defaults(func=cmd_analyze_dagger)

    add_installed_commands(sub)
    return parser


def _exit_on_sigterm(signum: int, frame) -> None:
    raise SystemExit(128 + signum)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # `kill PID` ends a command the way Ctrl-C does: cleanup runs, so `collect`, `eval` and `train dagger` shut
    # their worker processes down instead of leaving them orphaned. Saved work is written atomically either way.
    previous = signal.signal(signal.SIGTERM, _exit_on_sigterm) if threading.current_thread() is \
        threading.main_thread() else None
    try:
        return args.func(args)
    except (ConfigError, ValueError, FileNotFoundError) as e:
        print(f"gsmn {args.command}: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into `head` and the like
        sys.stderr.close()
        return 0
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
