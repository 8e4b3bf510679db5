"""The runner: one thread owns the simulator, the renderer and the policies (house style, practice 12).

The page and the HTTP API never touch them: they post commands (`Runner.post`) and get a `Future` back.
Between two steps of a live episode the runner answers commands, so the page stays responsive while an
episode flies, and pause, single step, cancel and counterfactual grounding all take effect at once. Episodes
fly through `gsmn.task.rollout.rollout`, the one rollout function evaluation and data collection use; its
`on_step` callback records each step (`app.live.recording`) and tells the listeners (the viewer).

The runner holds its checkpoints (`app.live.models.Checkpoints`) and its comparisons and forks
(`app.live.compare.Comparisons`); what flies an episode is `app.live.flight`.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import traceback
from collections import deque
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import numpy as np
import torch

from app.live import flight as flights
from app.live.commands import (
    MAX_ENV_ID,
    MAX_QUEUED,
    POLICIES,
    Cancel,
    CancelEpisode,
    CheckpointInfo,
    Command,
    Conflict,
    Ground,
    Grounding,
    NotFound,
    Pause,
    Resume,
    RunnerError,
    RunnerListener,
    SetSpeed,
    ShowEnv,
    StartEpisode,
    StepOnce,
    WorldShown,
)
from app.live.compare import Comparison, Comparisons
from app.live.flight import Flight, Unwind, flight_for, instruction_for_text, step_maps, task_for_start
from app.live.models import Checkpoints, LoadedModel
from app.live.recording import (
    CANCELLED,
    FAILED,
    FINISHED,
    PAUSED,
    RUNNING,
    Episode,
    EpisodeResult,
    EpisodeStore,
    StepRecord,
    jpeg_bytes,
)
from gsmn.config import RunConfig
from gsmn.task.baselines import ExpertPolicy
from gsmn.task.demo import DemoPathError
from gsmn.task.fork import FlightSnapshots
from gsmn.task.instructions import InstructionError
from gsmn.task.rollout import PolicyAction, RolloutStart, rollout, task_for_env
from gsmn.world.assets import load_catalogue
from gsmn.world.env import Env, Observation
from gsmn.world.spec import world_for_env

log = logging.getLogger("gsmn.dashboard")

class Runner:
    """Owns Env, renderer and policies on one thread. `checkpoint`: a folder, or a name under
    `checkpoints_root`; `require_checkpoint` makes a missing one an error instead of a message."""

    def __init__(self, config: RunConfig, checkpoint: str | Path | None = "gsmn", require_checkpoint: bool = False,
                 checkpoints_root: str | Path = "checkpoints", max_episodes: int = 16, max_queued: int = MAX_QUEUED,
                 episodes: EpisodeStore | None = None):
        self.config = config
        self.max_queued = max_queued
        self.checkpoints = Checkpoints(config, checkpoints_root, checkpoint, require_checkpoint)
        self.pairs = Comparisons(self)
        # in the dashboard, the record's store (app.jobs.kept_store.KeptStore)
        self.episodes = episodes if episodes is not None else EpisodeStore(max_episodes)
        self.listeners: list[RunnerListener] = []
        self.speed: float | None = None
        self.shown: WorldShown | None = None
        self.live: Episode | None = None
        self.paused = False
        self._step_budget = 0
        self._pending: deque[Episode] = deque()
        self._commands: queue.Queue[Command | None] = queue.Queue()
        self._closing = False
        self._ready: Future = Future()
        self._last_step = 0.0
        self.env: Env | None = None
        self.preview_env: Env | None = None  # renders a world asked for while an episode flies (made when needed)
        self._origin: str | None = None  # the origin of the command being done (app.live.commands.Command.origin)
        self.thread = threading.Thread(target=self._main, name="gsmn-runner", daemon=True)

    # -- the outside ------------------------------------------------------------------------------------------
    def start(self, timeout: float = 120.0) -> Runner:
        """Start the thread; wait until the simulator is up and the default checkpoint tried."""
        self.thread.start()
        self._ready.result(timeout)
        return self

    def post(self, command: Command) -> Future:
        if self._closing:
            command.future.set_exception(Conflict("the dashboard is shutting down"))
            return command.future
        self._commands.put(command)
        return command.future

    def call(self, command: Command, timeout: float = 60.0) -> Any:
        """Post and wait for the answer (raises what the command raised)."""
        return self.post(command).result(timeout)

    def close(self, timeout: float = 10.0) -> None:
        self._closing = True
        self._commands.put(None)
        if self.thread.is_alive():
            self.thread.join(timeout)

    @property
    def models(self) -> dict[str, LoadedModel]:
        """The models loaded, by their checkpoint's resolved path."""
        return self.checkpoints.models

    @property
    def default_model(self) -> str | None:
        return self.checkpoints.default

    @property
    def checkpoint_message(self) -> str:
        return self.checkpoints.message

    @property
    def has_model(self) -> bool:
        return self.checkpoints.default is not None

    def checkpoint_list(self) -> list[CheckpointInfo]:
        return self.checkpoints.listing()

    def comparison(self, comparison_id: int) -> Comparison | None:
        return self.pairs.store.get(comparison_id)

    # -- the thread -------------------------------------------------------------------------------------------
    def _main(self) -> None:
        try:
            self.env = Env(self.config, load_catalogue())
            self.checkpoints.load_default()
            self._ready.set_result(True)
        except BaseException as e:  # noqa: BLE001 - reported to whoever waits in start()
            self._ready.set_exception(e)
            return
        try:
            while not self._closing:
                if self._pending:
                    item = self._pending.popleft()
                    self.pairs.fly(item) if isinstance(item, Comparison) else self._fly(item)
                    continue
                command = self._commands.get()
                if command is None:
                    break
                self._handle(command)
        finally:
            for command in self._drain():
                command.future.set_exception(Conflict("the dashboard is shutting down"))
            for env in (self.env, self.preview_env):
                if env is not None:
                    env.close()

    def _drain(self) -> list[Command]:
        out = []
        while True:
            try:
                command = self._commands.get_nowait()
            except queue.Empty:
                return out
            if command is not None and not command.future.done():
                out.append(command)

    def _notify(self, method: str, *args: Any) -> None:
        for listener in list(self.listeners):
            try:
                getattr(listener, method)(*args)
            except Exception:  # noqa: BLE001 - a viewer bug must not stop the simulator
                log.error("listener %s.%s failed:\n%s", type(listener).__name__, method, traceback.format_exc())

    def _handle(self, command: Command) -> None:
        """Do one command and answer its future. Inside a live episode it may raise Unwind (after answering)."""
        name = type(command).__name__
        handler = getattr(self, "_do_" + name, None) or getattr(self.pairs, "do_" + name)
        self._origin = command.origin
        try:
            result = handler(command)
        except Unwind:
            raise
        except RunnerError as e:
            command.future.set_exception(e)
        except Exception as e:  # noqa: BLE001 - never let a bad request kill the runner
            log.error("command %s failed:\n%s", command, traceback.format_exc())
            command.future.set_exception(RunnerError(f"{type(e).__name__}: {e}"))
        else:
            if not command.future.done():
                command.future.set_result(result)

    # -- commands ---------------------------------------------------------------------------------------------
    def _check_env_id(self, env_id: int) -> None:
        if not isinstance(env_id, (int, np.integer)) or isinstance(env_id, bool):
            raise RunnerError(f"env_id must be an integer, got {env_id!r}")
        if not 0 <= env_id <= MAX_ENV_ID:
            raise RunnerError(f"env_id must be between 0 and {MAX_ENV_ID}, got {env_id}")

    def _do_ShowEnv(self, c: ShowEnv) -> WorldShown:
        """A world at its start, for the tab that asked. While an episode flies (maybe another tab's) it is
        rendered by a second simulator between two steps, so showing a world never ends anyone's episode."""
        self._check_env_id(c.env_id)
        world = world_for_env(int(c.env_id), self.config.world)
        try:
            task = task_for_env(int(c.env_id), self.config)
        except (DemoPathError, InstructionError):
            task = None
        if self.live is not None:
            if self.preview_env is None:
                self.preview_env = Env(self.config, self.env.catalogue)
            env = self.preview_env
        else:
            env = self.env
        obs = env.reset(world.env_id, task.instruction.text if task else None, world)
        shown = WorldShown(world, task, obs.image, tuple(float(v) for v in obs.pose.position), float(obs.pose.yaw),
                           obs.T_world_camera.astype(np.float32), origin=c.origin)
        self.shown = shown
        self._notify("on_world", shown)
        return shown

    def _do_StartEpisode(self, c: StartEpisode) -> Episode:
        episode = self._new_episode(c.env_id, c.instruction, c.policy, c.checkpoint, c.paused,
                                    check_queue=not c.preempt, world_edits=c.world_edits)
        if c.intervention is not None:  # e.g. a replay of an evaluation flown with a true map
            episode.intervention = c.intervention
            episode.intervene = flights.intervention_maker(self, c.intervention, episode.policy, episode.checkpoint)
        self.episodes.add(episode)
        self._enqueue(c, episode, episode)
        return episode

    def _check_queue(self) -> None:
        if len(self._pending) >= self.max_queued:
            last = self._pending[-1]
            last_id = last.episodes[-1].id if isinstance(last, Comparison) else last.id
            raise Conflict(f"{len(self._pending)} episodes already wait to fly (at most {self.max_queued}): wait for "
                           f"them, or cancel one (DELETE /api/episodes/{last_id})")

    def _enqueue(self, c: Command, item: Episode | Comparison, answer: Any) -> None:
        """Queue an episode (or a comparison's pair); with `c.preempt`, in front, ending the live one."""
        if getattr(c, "preempt", False):
            self._pending.appendleft(item)
            if self.live is not None:
                c.future.set_result(answer)
                raise Unwind
        else:
            self._pending.append(item)

    def _new_episode(self, env_id: int, text: str | None, policy: str, checkpoint: str | None,
                     paused: bool = False, check_queue: bool = False, world_edits: tuple = ()) -> Episode:
        """A checked episode (and, with `check_queue`, room for it in the queue), not yet stored or queued."""
        self._check_env_id(env_id)
        c = StartEpisode(env_id, text, policy, checkpoint, paused=paused, world_edits=tuple(world_edits))
        if c.policy not in POLICIES:
            raise RunnerError(f"policy must be one of {', '.join(POLICIES)}, got {c.policy!r}")
        model: LoadedModel | None
        if c.checkpoint is not None:
            model = self.checkpoints.model(c.checkpoint)
        elif self.default_model is not None:
            model = self.models[self.default_model]
        else:
            model = None
        if c.policy != "expert" and model is None:
            raise Conflict(f"no checkpoint to fly: {self.checkpoint_message} Choose the expert, or name a "
                           f"checkpoint.")
        if check_queue:
            self._check_queue()
        task = task_for_start(int(c.env_id), c.instruction, self.config, c.policy == "expert", c.world_edits)
        episode = Episode(id=self.episodes.new_id(), task=task, policy=c.policy,
                          system=model.policy.name if c.policy != "expert" else ExpertPolicy.name,
                          checkpoint=model.path.resolve().as_posix() if model else None,
                          horizon=self.config.task.horizon, start_paused=c.paused, origin=self._origin,
                          typed=c.instruction.strip() if c.instruction and c.instruction.strip() else None,
                          world_edits=tuple(c.world_edits))
        return episode

    def _do_Pause(self, c: Pause) -> bool:
        if self.live is not None and not self.paused:
            self.paused = True
            self.live.status = PAUSED
            self._notify("on_state", self.live, True)
        return self.paused

    def _do_Resume(self, c: Resume) -> bool:
        if self.live is not None and self.paused:
            self.paused = False
            self.live.status = RUNNING
            self._notify("on_state", self.live, False)
        return self.paused

    def _do_StepOnce(self, c: StepOnce) -> int:
        if self.live is None:
            raise Conflict("no live episode to step; start one (it can start paused)")
        if not self.paused:
            self._do_Pause(Pause())
        self._step_budget += 1
        return len(self.live.steps)

    def _do_Cancel(self, c: Cancel) -> bool:
        """End the live episode and drop the queued ones."""
        while self._pending:
            item = self._pending.popleft()
            for episode in item.episodes if isinstance(item, Comparison) else (item,):
                episode.status = CANCELLED
                self._notify("on_episode_end", episode)
        if self.live is None:
            return False
        c.future.set_result(True)
        raise Unwind

    def _do_CancelEpisode(self, c: CancelEpisode) -> Episode:
        """Drop a queued episode, or end the live one."""
        episode = self.episodes.get(c.episode_id)
        if episode is None:
            raise NotFound(self.episodes.missing(c.episode_id))
        pair = self.pairs.pending_pair(episode)
        if episode in self._pending or pair is not None:
            self._pending.remove(pair or episode)
            for e in pair.episodes if pair else (episode,):
                e.status = CANCELLED
                self._notify("on_episode_end", e)
            return episode
        if episode is not self.live and not self.pairs.flying(episode):
            raise Conflict(f"episode {episode.id} is {episode.status}: nothing to cancel")
        c.future.set_result(episode)
        raise Unwind

    def _do_SetSpeed(self, c: SetSpeed) -> float | None:
        if c.steps_per_second is not None and not c.steps_per_second > 0:
            raise RunnerError(f"steps_per_second must be positive or null, got {c.steps_per_second}")
        self.speed = c.steps_per_second
        self._notify("on_speed", self.speed)  # every tab's Speed box shows the one speed
        return self.speed

    def _do_Ground(self, c: Ground) -> Grounding:
        episode = self.episodes.get(c.episode_id)
        if episode is None:
            raise NotFound(self.episodes.missing(c.episode_id))
        if episode.checkpoint is None or episode.checkpoint not in self.models:
            raise Conflict(f"episode {c.episode_id} has no semantic map: no model watched it")
        n = len(episode.steps)
        if n == 0:
            raise Conflict(f"episode {c.episode_id} has no steps yet")
        step = n - 1 if c.step is None else c.step
        if not 0 <= step < n:
            raise RunnerError(f"step {step} is not recorded: episode {c.episode_id} has steps 0 to {n - 1}")
        maps = episode.steps[step].maps
        instruction = instruction_for_text(episode.task.world, c.text)
        model = self.models[episode.checkpoint]
        t0 = time.perf_counter()
        with torch.inference_mode():
            net = model.policy.model
            embedding = model.policy.embed(instruction.text)
            semantic = torch.from_numpy(maps.semantic_w.astype(np.float32))[None]  # (1, C_f, n, n)
            pose = torch.from_numpy(maps.pose.astype(np.float32))[None]  # (1, 3)
            g = net.ground(semantic, pose, embedding)
            drone = model.policy.config.drone
            result = Grounding(
                episode_id=episode.id, step=step, instruction=instruction,
                relevance_w=g.relevance_map_w[0].numpy().copy(), goal_w=g.goal_map_w[0].numpy().copy(),
                goal_r=g.goal_map_r[0].numpy().copy(), v=float(g.v[0]) * drone.max_forward_velocity,
                omega=float(g.omega[0]) * drone.max_yaw_rate, stop_probability=float(torch.sigmoid(g.stop_logit[0])),
                seconds=0.0)
        return _replace_seconds(result, time.perf_counter() - t0)

    # -- flying -----------------------------------------------------------------------------------------------
    def _flight(self, episode: Episode) -> Flight:
        """The policy that flies `episode`, with its own runtime state (two episodes may fly together)."""
        return flight_for(episode, self.models.get(episode.checkpoint) if episode.checkpoint else None, self.config)

    def _start(self, flight: Flight) -> RolloutStart | None:
        """None for an episode from the start corner; a fork is put at its step (`gsmn.task.fork`)."""
        episode, fork = flight.episode, flight.episode.fork
        episode.snapshots = FlightSnapshots()
        if fork is None:
            if episode.intervene is not None:  # from the first step: the substitute is made at the policy's reset
                flight.carrier.intervene(episode.intervene)
            return None
        from gsmn.task.fork import fork_start

        world = fork.world or episode.task.world  # the flight's: the model's memory is rebuilt in it
        self.env.reset(world.env_id, episode.instruction, world)
        flight.policy.reset(episode.task)
        if flight.expert is not None and fork.expert_task is not None:  # its path: the original's, or from the fork
            if not fork.same_expert and fork.step > 0:  # already in flight: no take-off ramp on its new path
                from dataclasses import replace

                flight.expert.config = replace(self.config, expert=replace(self.config.expert, ramp_waypoints=0))
            flight.expert.reset(fork.expert_task)
        start = fork_start(self.env, fork.snapshots, fork.step, fork.prefix, flight.carrier, fork.same_model,
                           flight.expert, fork.same_expert, episode.task.world)
        if episode.intervene is not None:  # from step t on, the model flies with the substitute map
            flight.carrier.intervene(episode.intervene, episode.task)
        episode.snapshots = fork.snapshots.prefix(fork.step, fork.same_model)
        return start

    def _fly(self, episode: Episode) -> None:
        flight = self._flight(episode)
        policy = flight.policy
        self.live = episode
        self.paused = episode.start_paused
        self._step_budget = 0
        episode.status = PAUSED if self.paused else RUNNING
        episode.started = time.perf_counter()
        self._last_step = 0.0
        self._notify("on_episode_start", episode)
        try:
            record = rollout(self.env, policy, episode.task, episode.horizon,
                             on_step=lambda obs, action: self._on_step(episode, obs, action, flight),
                             success_radius=self.config.task.success_radius, start=self._start(flight))
            last = episode.steps[-1] if episode.steps else None
            episode.result = EpisodeResult.of(record, last.decisive_stop_probability if last else None)
            episode.status = FINISHED
        except Unwind:
            episode.status = CANCELLED
        except Exception as e:  # noqa: BLE001 - the episode fails, the dashboard lives on
            log.error("episode %d failed:\n%s", episode.id, traceback.format_exc())
            episode.status, episode.error = FAILED, f"{type(e).__name__}: {e}"
        finally:
            episode.finished = time.perf_counter()
            self.live = None
            self.paused = False
            self._notify("on_episode_end", episode)

    def _on_step(self, episode: Episode, obs: Observation, action: PolicyAction, flight: Flight,
                 pace: bool = True) -> None:
        """Record a step; with `pace`, answer commands until the next is due (a comparison paces its pair)."""
        watcher = flight.watcher
        episode.snapshots.record(self.env, flight.carrier, flight.expert)
        p = obs.pose.position
        record = StepRecord(step=obs.step, time=obs.time, position=(float(p[0]), float(p[1]), float(p[2])),
                            yaw=float(obs.pose.yaw), T_world_camera=obs.T_world_camera.astype(np.float32),
                            camera_jpeg=jpeg_bytes(obs.image), v=float(action.forward_velocity),
                            omega=float(action.yaw_rate), stop=bool(action.stop),
                            maps=step_maps(watcher) if watcher is not None else None,
                            stop_probability=action.stop_probability)
        episode.steps.append(record)
        if episode.first_frame is None:
            episode.first_frame = time.perf_counter()
        self._notify("on_step", episode, record)
        if pace and not action.stop and obs.step < episode.horizon:
            self._between_steps(episode)

    def _between_steps(self, episode: Episode) -> None:
        """Answer commands until the next step is due: at once, after the speed limit's interval, or (paused)
        after a single-step command."""
        while True:
            if self._closing:
                raise Unwind
            if self.paused:
                if self._step_budget > 0:
                    self._step_budget -= 1
                    break
                timeout: float | None = None
            else:
                due = self._last_step + 1.0 / self.speed if self.speed else 0.0
                timeout = due - time.perf_counter()
            try:
                command = self._commands.get(timeout=timeout) if timeout is None or timeout > 0 \
                    else self._commands.get_nowait()
            except queue.Empty:
                break
            if command is None:
                self._commands.put(None)  # for the main loop, after unwinding
                raise Unwind
            self._handle(command)
        self._last_step = time.perf_counter()



def _replace_seconds(g: Grounding, seconds: float) -> Grounding:
    from dataclasses import replace

    return replace(g, seconds=seconds)
