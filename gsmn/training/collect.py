"""Data collection: fly episodes and record them with the expert's labels (paper: Learning, Algorithm 1).

`MixturePolicy` executes, at every step, the expert's action with probability beta and the learner's
otherwise (DAggerFM's per-step mixture; beta = 1 is plain expert data), and always records the expert's
action as the label. A rollout is cut when the drone strays more than `max_deviation` from the
demonstration path (the original's 4.5 m). `collect_expert` fills an EpisodeStore from the expert over
many environments in parallel worker processes and resumes where a killed run stopped.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from gsmn.config import RunConfig
from gsmn.executor import ExecutorOptions, make_executor
from gsmn.model.batch import EpisodeSample
from gsmn.task.baselines import ExpertPolicy
from gsmn.task.rollout import EpisodeRecord, Policy, PolicyAction, Task, rollout, task_for_env
from gsmn.training.store import EpisodeStore
from gsmn.world.env import Env, Observation


class MixturePolicy:
    """Per step: the expert acts with probability beta, else the learner; the label is always the expert's."""

    name = "mixture"
    needs_images = True

    def __init__(self, config: RunConfig, learner: Policy | None = None, beta: float = 1.0,
                 rng: np.random.Generator | None = None, max_deviation: float | None = None):
        if learner is None and beta < 1.0:
            raise ValueError("a mixture with beta < 1 needs a learner")
        self.config = config
        self.expert = ExpertPolicy(config)
        self.learner = learner
        self.beta = beta
        self.rng = rng or np.random.default_rng()
        self.max_deviation = max_deviation
        self.label: np.ndarray | None = None  # (3,) v_norm, omega_norm, stop of the last step
        self.expert_steps = self.learner_steps = 0
        self.cut = False  # the last rollout was cut for straying from the path

    def reset(self, task: Task) -> None:
        self.expert.reset(task)
        if self.learner is not None:
            self.learner.reset(task)
        self.expert_steps = self.learner_steps = 0
        self.cut = False

    def act(self, obs: Observation) -> PolicyAction:
        drone = self.config.drone
        expert_action = self.expert.act(obs)
        self.label = np.array([expert_action.forward_velocity / drone.max_forward_velocity,
                               expert_action.yaw_rate / drone.max_yaw_rate, float(expert_action.stop)], np.float32)
        # The learner sees every observation (its map must integrate them all), acting or not.
        learner_action = self.learner.act(obs) if self.learner is not None else None
        if learner_action is None or self.rng.random() < self.beta:
            action = expert_action
            self.expert_steps += 1
        else:
            action = learner_action
            self.learner_steps += 1
        if self.max_deviation is not None and self.expert.expert.distance_to_path(obs.pose.position[:2]) > (
                self.max_deviation):
            self.cut = True
            return PolicyAction(0.0, 0.0, stop=True)  # cut the rollout here; the label stays the expert's
        return action


def record_episode(env: Env, policy: MixturePolicy, task: Task, horizon: int) -> EpisodeSample:
    """Fly one episode with `policy` and return it with the expert's label at every observation."""
    return fly_and_record(env, policy, task, horizon)[0]


def fly_and_record(env: Env, policy: MixturePolicy, task: Task, horizon: int
                   ) -> tuple[EpisodeSample, EpisodeRecord]:
    """`record_episode`, and the flight's outcome as `gsmn eval` scores it (success, stop, distances)."""
    images, T_world_camera, poses, labels = [], [], [], []

    def on_step(obs: Observation, action: PolicyAction) -> None:
        images.append(obs.image)
        T_world_camera.append(obs.T_world_camera)
        poses.append((obs.pose.position[0], obs.pose.position[1], obs.pose.yaw))
        labels.append(policy.label)

    record = rollout(env, policy, task, horizon, on_step=on_step)
    sample = EpisodeSample(world=task.world, instruction=task.instruction, images=np.stack(images),
                           T_world_camera=np.stack(T_world_camera).astype(np.float32), K=env.sim.K.astype(np.float32),
                           poses=np.array(poses, np.float32), actions=np.stack(labels))
    return sample, record


def episode_key(env_id: int) -> str:
    return f"env_{env_id:06d}"


# -- parallel expert collection ---------------------------------------------------------------------
_worker: dict = {}


def _init_worker(config: RunConfig, root: str) -> None:
    _worker.update(config=config, env=Env(config), store=EpisodeStore(root), policy=MixturePolicy(config))


def _collect_one(env_id: int) -> tuple[int, int]:
    """Fly and write one expert episode; (env_id, frames), or frames 0 where another collector of the same store
    wrote it since the list was made."""
    if episode_key(env_id) in _worker["store"]:
        return env_id, 0
    config: RunConfig = _worker["config"]
    sample = record_episode(_worker["env"], _worker["policy"], task_for_env(env_id, config), config.task.horizon)
    _worker["store"].write(episode_key(env_id), sample, meta={"env_id": env_id, "source": "expert"})
    return env_id, len(sample.images)


def collect_expert(store: EpisodeStore, env_ids: Sequence[int], config: RunConfig, workers: int = 1,
                   on_episode: Callable[[int, int], None] | None = None,
                   executor_options: ExecutorOptions | None = None) -> list[int]:
    """Record the expert on every environment not yet in the store; returns the ids collected now. Episodes fly
    on `workers` workers of the executor `executor_options` names (default: processes on this host)."""
    todo = [e for e in env_ids if episode_key(e) not in store]
    executor = make_executor(executor_options, workers, _init_worker, (config, str(store.root)),
                             in_process=lambda: (_init_worker(config, str(store.root)), _close_worker)[1])
    try:
        for env_id, frames in executor.map(_collect_one, todo):
            if on_episode:
                on_episode(env_id, frames)
    finally:  # stopped early (SIGTERM, Ctrl-C, an error): finish the episodes in flight, start no more
        executor.close()
    return todo


def _close_worker() -> None:
    _worker.pop("env").close()
