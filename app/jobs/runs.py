"""What a DAggerFM fine-tuning run launched from the dashboard runs, and how its folder reads (`JobManager.start_run`
launches it, its monitor reads it):

    gsmn collect (the expert demonstrations DAggerFM's dataset starts from, when missing; and the dev split's, which
                  it validates on after every iteration)
    && gsmn train dagger --init C --data STORE --dev DEV --run DIR [--env-ids ...] (paper: Algorithm 1)

each with `--config FOLDER/config.json`, the run's configuration (`app.jobs.settings.run_config`).
"""

from __future__ import annotations

import shlex
from pathlib import Path

from app.jobs.db import Run
from app.jobs.settings import DEV_EPISODES, RunSettings, expert_store_key
from gsmn.config import RunConfig

DAGGER_KINDS = ("gsmn", "gsmn-no-plan", "gs-fpv", "gs-fpv-mem")  # the models DAggerFM trains


def run_command(python: str, root: Path, folder: Path, config: RunConfig, settings: RunSettings, init: Path,
                env_ids: list[int] | None, expert_data: Path | None) -> list[str]:
    """The run's command, in its job folder under the data folder `root`: collect what it lacks, then train."""
    from gsmn.world.spec import split_env_ids

    # the expert demonstrations the dataset starts from: a store named in the settings; else those of the chosen
    # environments, in the run's folder; else the train split's, shared by runs with the same settings
    if expert_data is not None:
        store = expert_data
    elif env_ids is not None:
        store = folder / "expert"
    else:
        store = root / "expert" / expert_store_key(config)
    flags = ["--config", str(folder / "config.json")]

    def collect(out: Path, ids: list[int]) -> str:
        return shlex.join([python, "-m", "gsmn.cli", "collect", "--out", str(out), "--env-ids", ",".join(map(str, ids)),
                           "--workers", str(settings.workers), *flags])

    parts = []
    if settings.expert_data is None:
        parts.append(collect(store, env_ids if env_ids is not None else split_env_ids("train", settings.dataset_size)))
    # expert episodes of the dev split, validated on after every iteration: the per-objective accuracies the
    # Fine-tune tab plots as the run trains (the paper's Figure 4), shared by runs with the same settings
    dev = root / "expert_dev" / expert_store_key(config)
    parts.append(collect(dev, split_env_ids("dev", DEV_EPISODES.get(settings.preset, DEV_EPISODES["tiny"]))))
    dagger = [python, "-m", "gsmn.cli", "train", "dagger", "--init", str(init), "--data", str(store),
              "--dev", str(dev), "--run", str(folder / "run"), *flags]
    if env_ids is not None:
        dagger += ["--env-ids", ",".join(map(str, env_ids))]
    parts.append("exec " + shlex.join(dagger))
    return ["sh", "-c", " && ".join(parts)]


def run_progress(folder: Path, row: Run) -> tuple[dict, list[dict]]:
    """Where a run is (phase, iteration, overall fraction, a line for people) and its per-iteration log so far,
    from its folder: the expert store while collecting, then what the trainer reports (`read_progress`)."""
    from gsmn.training.run import read_progress

    iterations = int(row.settings["iterations"])
    p = read_progress(folder / "run", iterations)
    if p is None:
        return {"phase": "expert data", "iteration": 0, "iterations": iterations, "fraction": 0.0,
                "text": "collecting the expert demonstrations the dataset starts from"}, []
    text = f"iteration {min(p.done + 1, iterations)} of {iterations}"
    if p.done >= iterations:
        text = f"{iterations} iterations done"
    elif p.rollouts is not None:
        text += f": rollouts {p.rollouts[0]}/{p.rollouts[1]} (beta {p.beta:.2f})"
    elif p.batches is not None:
        text += f": training, batch {p.batches[0]}/{p.batches[1]}" + (f", loss {p.loss:.3f}" if p.loss is not None
                                                                         else "")
    elif p.iteration is not None:
        text = f"iteration {p.iteration} of {iterations}: {p.phase}"
    else:
        text += f": {p.phase}"
    out = {"phase": p.phase, "iteration": p.done, "iterations": iterations, "fraction": p.fraction, "text": text}
    if p.log:
        out["loss"] = p.log[-1].get("train", {}).get("loss")
    return out, p.log


def run_complete(folder: Path, row: Run, metrics: list[dict]) -> bool:
    """Whether a run's folder holds all its iterations and a checkpoint that loads."""
    from gsmn.model.checkpoint import CheckpointError, load_checkpoint

    if len(metrics) < row.settings["iterations"]:
        return False
    try:
        load_checkpoint(folder / "run" / "checkpoint")
        return True
    except (CheckpointError, OSError, ValueError):
        return False
