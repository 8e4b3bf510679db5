"""What the Table 2 programme trains, and where each of its systems stands: the systems (`SYSTEMS`, `BY_NAME`,
`TABLE1`, `MODULE_ABLATIONS`), the `Recipe` they share (`RECIPES`, `system_configs`, `environments`), and the
reading of a stage copy (`read_stage`, `describe_stage`, `trained`, `finished`, `training_stage`, `partial_path`,
`kept_partial`).

Light on purpose: it imports neither training, evaluation nor the model (no torch), so the dashboard reads it to
label the checkpoints in checkpoints/table2/. The programme that trains and evaluates the systems is
`gsmn.experiments.programme`, the tables of their kept evaluations `gsmn.experiments.table`, the command line
(`gsmn experiment table2`) `gsmn.experiments.table2`.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gsmn.config import RunConfig, preset, with_overrides

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_SHIP = ROOT / "checkpoints" / "table2"


@dataclass(frozen=True)
class Recipe:
    """The training and evaluation budget shared by every system (docs/training.md, "The ablation programme")."""

    train_envs: int = 600  # expert episodes for supervised learning: the first N train environments
    dev_envs: int = 40  # expert episodes on dev, for the per-epoch validation figures (Figure 4)
    epochs: int = 16
    learning_rate: float = 1e-3  # supervised (the paper's)
    iterations: int = 15  # DAggerFM
    rollouts: int = 48  # N_D
    dataset_size: int = 192  # M; the initial D comes from expert episodes in M fresh train environments
    beta0: float = 0.5
    dagger_learning_rate: float = 3e-4
    fresh_envs: int = 2400  # the train environments after the first `train_envs` that DAggerFM flies in
    eval_envs: int = 300  # the first N dev environments, flown plainly
    table1_envs: int = 500  # the first N test environments (Table 1's), flown by the TABLE1 systems
    publish_every_epochs: int = 4
    publish_every_iterations: int = 5
    control_gate: float = 60.0  # the control's dev success (%) below which the drops would be noise: stop there
    preset: str = "paper"
    # how the camera draws shadows (gsmn/world/shadows.py): every system of the programme trains and is evaluated
    # under the look its first systems had, MuJoCo's shadow passes, whatever the library's default
    shadow_method: str = "mujoco"

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def base_config(self) -> RunConfig:
        """The configuration every system of the recipe starts from: its preset, rendered its way."""
        return with_overrides(preset(self.preset), {"camera.shadow_method": self.shadow_method})


RECIPES = {
    "paper": Recipe(),
    # seconds per stage: the tests run the whole programme with it
    "tiny": Recipe(train_envs=3, dev_envs=2, epochs=2, iterations=2, rollouts=2, dataset_size=2, fresh_envs=4,
                   eval_envs=2, table1_envs=1, publish_every_epochs=1, publish_every_iterations=1, control_gate=0.0,
                   preset="tiny"),
}


@dataclass(frozen=True)
class System:
    name: str  # folder name under SHIP and OUT
    label: str  # as the dashboard and the table name it
    kind: str  # model kind (gsmn.model.models.KINDS)
    switch: dict[str, Any] = field(default_factory=dict)  # the config fields this system changes, by dotted path


SYSTEMS = (
    System("gsmn", "GSMN", "gsmn"),
    # the kind marks the goal head as untrained for attribution and evaluation; its loss is the control's without J_plan
    System("no-plan", "GSMN without J_plan", "gsmn-no-plan", {"loss.goal": False}),
    System("no-ground", "GSMN without J_ground", "gsmn", {"loss.grounding": False}),
    System("no-lang", "GSMN without J_lang", "gsmn", {"loss.language": False}),
    System("no-percept", "GSMN without J_percept", "gsmn", {"loss.perception": False}),
    # the original code's 0.5 m standard deviation on x, y, z, fresh at every forward pass, in training and flight;
    # no yaw noise, as the paper's eta = [eta_x, eta_y, eta_z, 0, 0, 0] (docs/training.md)
    System("pose-noise", "GSMN + pose noise", "gsmn", {"model.pose_noise_std": 0.5}),
    # the original code's -J_ground and -J_goal: the filter itself replaced by an identity, its loss gone with it
    # (docs/model.md, "Removing a module")
    System("no-ground-module", "GSMN without the grounding filter (as the original code)", "gsmn",
           {"model.grounding_filter": False, "loss.grounding": False}),
    System("no-plan-module", "GSMN without the goal filter (as the original code)", "gsmn",
           {"model.goal_filter": False, "loss.goal": False}),
    # Table 1's first-person baselines at the control's recipe (their kinds train without J_plan themselves)
    System("gs-fpv", "GS-FPV", "gs-fpv"),
    System("gs-fpv-mem", "GS-FPV-MEM", "gs-fpv-mem"),
)
BY_NAME = {s.name: s for s in SYSTEMS}
# flown on Table 1's test environments too: the -J_plan row of Table 1 beside a GSMN of the same recipe
TABLE1 = ("gsmn", "no-plan", "gs-fpv", "gs-fpv-mem")
# the two kinds of ablation side by side (docs/results.md): the objective removed, and the module removed with it
MODULE_ABLATIONS = {"no-ground": "no-ground-module", "no-plan": "no-plan-module"}


def system_configs(system: System, recipe: Recipe, threads: int = 2,
                   device: str = "cpu") -> tuple[RunConfig, RunConfig]:
    """The supervised and the DAggerFM configuration of `system` under `recipe`. `threads` and `device` are settings a
    run may change when it resumes (`gsmn.training.run.ADJUSTABLE`): on a GPU the episodes of the next batches are
    read on 4 threads while one trains (`train.prefetch`: the same batches, so the same run)."""
    base = recipe.base_config()
    common = {"train.batch_size": "1", "train.threads": str(threads), "train.device": device,
              "train.prefetch": "0" if device == "cpu" else "4", "train.epochs": str(recipe.epochs),
              "dagger.iterations": str(recipe.iterations), "dagger.rollouts_per_iteration": str(recipe.rollouts),
              "dagger.dataset_size": str(recipe.dataset_size), "dagger.beta0": str(recipe.beta0),
              "dagger.workers": "1" if threads == 1 else "2"}
    common.update({path: str(value) for path, value in system.switch.items()})
    supervised = with_overrides(base, {**common, "train.learning_rate": str(recipe.learning_rate)})
    dagger = with_overrides(base, {**common, "train.learning_rate": str(recipe.dagger_learning_rate)})
    return supervised, dagger


def environments(recipe: Recipe) -> dict[str, list[int]]:
    from gsmn.world.spec import split_env_ids

    train = split_env_ids("train", recipe.train_envs + recipe.fresh_envs)
    fresh = train[recipe.train_envs:]
    return {"train": train[:recipe.train_envs], "dev": split_env_ids("dev", recipe.dev_envs),
            "seed": fresh[:recipe.dataset_size], "fresh": fresh, "eval": split_env_ids("dev", recipe.eval_envs),
            "table1": split_env_ids("test", recipe.table1_envs)}


# the two evaluations: the dev environments of Table 2 (every system), the test environments of Table 1 (TABLE1)
EVALUATIONS = {"dev": ("eval", "evaluation.json", "evaluation_full.json", "record"),
               "test": ("table1", "table1.json", "table1_full.json", "record_table1")}


def partial_path(ship: Path, split: str) -> Path:
    """Where an unfinished evaluation's compact episodes are kept beside the stage copy, chunk by chunk."""
    return ship / EVALUATIONS[split][1].replace(".json", ".partial.json")


def stage_key(stage: dict | None) -> dict:
    """What tells one stage copy from another: its stage, epoch (iteration) and epochs."""
    return {k: (stage or {}).get(k) for k in ("stage", "epoch", "epochs")}


def chunk_tag(stage: dict | None) -> str:
    """That key in a file name: "dagger15of15"."""
    key = stage_key(stage)
    return f"{key['stage']}{key['epoch']}of{key['epochs']}"


def kept_partial(ship: Path, split: str, ids: list[int] | None = None) -> dict:
    """The kept partial evaluation of this stage copy (on these environments); empty if none, or of another copy."""
    try:
        kept = json.loads(partial_path(ship, split).read_text())
    except (OSError, ValueError):
        return {"episodes": []}
    if (ids is not None and kept.get("env_ids") != ids) or kept.get("stage") != stage_key(read_stage(ship)):
        return {"episodes": []}
    return kept


# -- stage copies ---------------------------------------------------------------------------------------------
def read_stage(ship: Path) -> dict | None:
    try:
        return json.loads((ship / "stage.json").read_text())
    except (OSError, ValueError):
        return None


def describe_stage(stage: dict, ship: Path) -> str:
    """A stage copy as a person reads it: "GSMN without J_ground (Table 2: 52.0 % on 300 dev)", or where its
    training stands."""
    label = stage.get("label") or stage.get("system", ship.name)
    if stage.get("evaluated"):
        try:
            summary = json.loads((ship / "evaluation.json").read_text())["summary"]
            return f"{label} (Table 2: {summary['success']:.1f} % on {summary['count']} dev)"
        except (OSError, ValueError, KeyError):
            pass
    if trained(stage):
        return f"{label} (Table 2, trained; not yet evaluated)"
    return f"{label} (Table 2, in training: {training_stage(stage)})"


def trained(stage: dict) -> bool:
    return stage.get("stage") == "dagger" and stage.get("epoch") == stage.get("epochs")


def finished(stage: dict | None, recipe: Recipe) -> bool:
    """Trained to the end of this recipe (not of a shorter one extended since)."""
    return bool(stage) and trained(stage) and stage.get("epochs") == recipe.iterations


def training_stage(stage: dict) -> str:
    """"supervised epoch 8 of 16", "DAggerFM iteration 7 of 15"."""
    name, what = ("supervised", "epoch") if stage.get("stage") == "supervised" else ("DAggerFM", "iteration")
    return f"{name} {what} {stage.get('epoch')} of {stage.get('epochs')}"


def stage_order(stage: dict | None) -> tuple[int, int]:
    """How far a stage copy's training is: supervised before DAggerFM, then by epoch (iteration)."""
    if not stage:
        return (-1, -1)
    return (0 if stage.get("stage") == "supervised" else 1, int(stage.get("epoch", 0)))

