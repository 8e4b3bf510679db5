"""What flies an episode on the runner thread: the policy with its watcher, the task typed text asks for, the maps
kept per step, and the exception that ends a live episode early.

A model "watches" every episode when a checkpoint is loaded: flying itself, or beside the expert, whose episodes
then show what the model would have mapped, grounded and done.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from app.live.commands import RunnerError
from app.live.recording import Episode, StepMaps
from gsmn.config import RunConfig
from gsmn.task.baselines import ExpertPolicy
from gsmn.task.demo import DemoPathError
from gsmn.task.edits import EditError, edit_world, edited_task
from gsmn.task.instructions import Instruction, InstructionError
from gsmn.task.rollout import PolicyAction, Task, task_for_env
from gsmn.task.rollout import task_for_text as text_task
from gsmn.task.understand import parse_instruction
from gsmn.world.env import Observation
from gsmn.world.spec import WorldSpec, world_for_env

# Maps of the record the dashboard does not keep per step: the image features and their projection are the
# largest (about 100 kB a step together, more than all the others), and the semantic map holds what they add up to.
NOT_KEPT = ("features_c", "projected_features_w")


class Unwind(Exception):
    """Raised inside a live episode's step callback to end it early (cancel, preempt, another world, close)."""


class WatchedPolicy:
    """The expert flies while the model watches (acts on every observation but is not obeyed), so an
    expert episode shows the model's maps too."""

    needs_images = True

    def __init__(self, actor, watcher):
        self.actor, self.watcher = actor, watcher
        self.name = actor.name

    def reset(self, task: Task) -> None:
        self.actor.reset(task)
        self.watcher.reset(task)

    def act(self, obs: Observation) -> PolicyAction:
        self.watcher.act(obs)
        return self.actor.act(obs)


@dataclass
class Flight:
    """An episode and what flies it: `policy` (what rollout calls), the model whose maps are recorded (`watcher`),
    the part whose state carries from step to step (`carrier`: the model, or the mirror ensemble) and the expert
    when it flies."""

    episode: Episode
    policy: Any
    watcher: Any | None
    carrier: Any | None
    expert: ExpertPolicy | None


def flight_for(episode: Episode, model, config: RunConfig) -> Flight:
    """The policy that flies `episode` with its own runtime state (two episodes may fly together); `model`: the
    `app.live.models.LoadedModel` that watches, or None."""
    from gsmn.model.policy import ModelPolicy

    watcher = None
    if model is not None:
        p = model.policy
        watcher = ModelPolicy(p.model, p.vocabulary, p.config, p.name)
    expert = None
    if episode.policy == "model":
        policy = carrier = watcher
    elif episode.policy == "mirror":  # the maps recorded are the unmirrored copy's (MirrorEnsemble)
        from gsmn.model.policy import MirrorEnsemble

        policy = carrier = MirrorEnsemble(watcher)
    else:
        expert = ExpertPolicy(config)
        policy = WatchedPolicy(expert, watcher) if watcher is not None else expert
        carrier = watcher
    return Flight(episode, policy, watcher, carrier, expert)


def instruction_for_text(world: WorldSpec, text: str) -> Instruction:
    """The instruction typed text gives in `world` (`gsmn.task.understand`), or why it gives none."""
    try:
        return parse_instruction(text, world)
    except InstructionError as e:
        raise RunnerError(str(e)) from e


def task_for_text(world: WorldSpec, text: str, config: RunConfig, need_path: bool = False) -> Task:
    """`gsmn.task.rollout.task_for_text` with its errors as the runner's: a straight line where the planner finds no
    path, unless `need_path` (for the expert who follows the path): then an error."""
    try:
        return text_task(world, text, config, need_path)
    except InstructionError as e:
        raise RunnerError(str(e)) from e
    except DemoPathError as e:
        raise RunnerError(f"the expert has no path to that goal ({e}); try another side") from e


def task_for_start(env_id: int, text: str | None, config: RunConfig, need_path: bool,
                   world_edits: tuple = ()) -> Task:
    """The task an episode flies: the environment's own instruction, or the typed one, in the environment's world with
    `world_edits` made (gsmn.task.edits: the environment's instruction follows its landmark; a typed one is read in
    the edited world). An edit that cannot stand, or an instruction it leaves unflyable, is a RunnerError."""
    world = world_for_env(env_id, config.world)
    try:
        if text is None or not text.strip():
            try:
                task = task_for_env(env_id, config)
            except DemoPathError as e:
                raise RunnerError(f"environment {env_id} has no instruction with a demonstration path ({e})") from e
            return edited_task(task, world_edits, config)
        return task_for_text(edit_world(world, world_edits, config)[0] if world_edits else world, text, config,
                             need_path)
    except EditError as e:
        raise RunnerError(str(e)) from e


def step_maps(policy) -> StepMaps | None:
    """The maps of the model's last step, kept per step as float16 (all but NOT_KEPT), and what it decided."""
    out = policy.last_outputs
    if out is None:
        return None
    drone = policy.config.drone

    def f16(t: torch.Tensor) -> np.ndarray:
        return t[0, 0].to(torch.float16).numpy().copy()

    maps = {name: f16(t) for name, t in out.maps().items() if name not in NOT_KEPT}
    return StepMaps(maps=maps, pose=out.poses[0, 0].float().numpy().copy(),
                    v=float(out.v[0, 0]) * drone.max_forward_velocity,
                    omega=float(out.omega[0, 0]) * drone.max_yaw_rate,
                    stop_probability=float(torch.sigmoid(out.stop_logit[0, 0])))


def intervention_maker(runner, intervention, policy: str, checkpoint: str | None):
    """What makes an episode's map substitute (`gsmn.analysis.intervention`) for `runner`'s loaded model
    `checkpoint`, or a RunnerError saying why there is none: the model must fly (not the expert, not an ensemble)
    and be a GSMN with both filters and map codes beside its weights."""
    from gsmn.analysis.intervention import InterventionError, InterventionMaker, check_model, codes_for

    if policy != "model" or checkpoint is None or checkpoint not in runner.models:
        raise RunnerError("a map intervention changes the maps the model flies with: fly it with policy 'model' and "
                          "a GSMN checkpoint")
    model = runner.models[checkpoint]
    try:
        check_model(model.policy.model)
        codes = codes_for(model.path)
    except InterventionError as e:
        raise RunnerError(str(e)) from e
    return InterventionMaker(intervention, codes, model.policy.model.config.model.map_size,
                             runner.config.task.success_radius)
