"""The runner: one thread owns the simulator, the renderer and the policies (house style, practice 12).

The page and the HTTP API never touch them: they post commands (`Runner.post`) and get a `Future` back.
Between two steps of a live episode the runner answers commands, so the page stays responsive while an
episode flies, and pause, single step, cancel and counterfactual grounding all take effect at once. Episodes
fly through `gsmn.task.rollout.rollout`, the one rollout function evaluation and data collection use; its
`on_step` callback records each step (`app.live.recording`) and tells the listeners (the viewer).

A model "watches" every episode when a checkpoint is loaded: flying itself, or beside the expert, whose
episodes then show what the model would have mapped, grounded and done.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from app.render.colors import jpeg_bytes
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
from app.live.compare import ComparingRunner, Comparison
from app.render.layers import NOT_KEPT, MapHeads
from app.live.recording import (
    CANCELLED,
    FAILED,
    FINISHED,
    PAUSED,
    RUNNING,
    Episode,
    EpisodeResult,
    EpisodeStore,
    StepMaps,
    StepRecord,
)
from gsmn.config import RunConfig
from gsmn.task.baselines import ExpertPolicy
from gsmn.task.demo import DemoPathError, demonstration_path, resample
from gsmn.task.fork import FlightSnapshots
from gsmn.task.instructions import Instruction, InstructionError, parse_instruction
from gsmn.task.rollout import PolicyAction, RolloutStart, Task, rollout, task_for_env
from gsmn.world.assets import load_catalogue
from gsmn.world.env import Env, Observation
from gsmn.world.spec import WorldSpec, world_for_env

log = logging.getLogger("gsmn.dashboard")

class _Unwind(Exception):
    """Raised inside a live episode's step callback to end it early (cancel, preempt, another world, close)."""


@dataclass
class LoadedModel:
    name: str
    path: Path
    policy: Any  # gsmn.model.policy.ModelPolicy
    heads: MapHeads
    meta: dict


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


def _straight_task(world: WorldSpec, instruction: Instruction, spacing: float) -> Task:
    return Task(world, instruction, resample(np.stack([world.start_position, instruction.goal]), spacing))


# -- the runner -----------------------------------------------------------------------------------------------
def checkpoint_label(name: str, path: Path) -> str:
    """A readable name: a Table 2 system's label and where its programme stands (`gsmn experiment table2`), else
    the checkpoint's name."""
    from gsmn.experiments.table2 import describe_stage, read_stage

    stage = read_stage(path)
    return describe_stage(stage, path) if stage else name


class Runner(ComparingRunner):
    """Owns Env, renderer and policies on one thread. `checkpoint`: a folder, or a name under
    `checkpoints_root`; `require_checkpoint` makes a missing one an error instead of a message."""

    def __init__(self, config: RunConfig, checkpoint: str | Path | None = "gsmn", require_checkpoint: bool = False,
                 checkpoints_root: str | Path = "checkpoints", max_episodes: int = 16, max_queued: int = MAX_QUEUED,
                 episodes: EpisodeStore | None = None):
        self.config = config
        self.max_queued = max_queued
        self.checkpoints_root = Path(checkpoints_root)
        self.default_ref = str(checkpoint) if checkpoint is not None else None
        self.require_checkpoint = require_checkpoint
        self.episodes = episodes if episodes is not None else EpisodeStore(max_episodes)  # app.jobs.kept.KeptStore
        self.listeners: list[RunnerListener] = []
        self.models: dict[str, LoadedModel] = {}  # by resolved path
        self.extra_checkpoints: Callable[[], dict[str, Path]] | None = None  # e.g. fine-tuning runs', by name
        self.default_model: str | None = None  # key into self.models
        self.checkpoint_message = ""
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
    def has_model(self) -> bool:
        return self.default_model is not None

    def checkpoint_list(self) -> list[CheckpointInfo]:
        """Checkpoint folders under checkpoints_root, the default one, and any loaded."""
        import json

        found: dict[str, Path] = {}
        if self.checkpoints_root.is_dir():
            for meta in sorted(self.checkpoints_root.glob("*/meta.json")):
                found[meta.parent.name] = meta.parent
            for meta in sorted(self.checkpoints_root.glob("*/*/meta.json")):  # a group, e.g. table2/no-ground
                if not (meta.parent.parent / "meta.json").is_file():
                    found[f"{meta.parent.parent.name}/{meta.parent.name}"] = meta.parent
        if self.default_ref is not None and self.default_ref not in found:
            path = self._path_of(self.default_ref)  # e.g. a folder given by its path: listed once, by its name
            if path.is_dir() and path.resolve() not in {p.resolve() for p in found.values()}:
                found[self.default_ref] = path
        for name, path in (self.extra_checkpoints() if self.extra_checkpoints else {}).items():
            found.setdefault(name, path)
        known = {p.resolve() for p in found.values()}
        for m in self.models.values():
            if m.path.resolve() not in known:
                found.setdefault(m.name, m.path)
        default_key = self.default_model
        out = []
        for name, path in found.items():
            key = str(path.resolve())
            try:
                meta = json.loads((path / "meta.json").read_text())
                error = None
            except (OSError, ValueError) as e:
                meta, error = {}, f"meta.json unreadable: {e}"
            out.append(CheckpointInfo(name=name, path=str(path), kind=meta.get("kind"), created=meta.get("created"),
                                      loaded=key in self.models, default=key == default_key, error=error,
                                      metrics=meta.get("metrics") or {}, label=checkpoint_label(name, path)))
        return out

    # -- the thread -------------------------------------------------------------------------------------------
    def _main(self) -> None:
        try:
            self.env = Env(self.config, load_catalogue())
            self._load_default()
            self._ready.set_result(True)
        except BaseException as e:  # noqa: BLE001 - reported to whoever waits in start()
            self._ready.set_exception(e)
            return
        try:
            while not self._closing:
                if self._pending:
                    item = self._pending.popleft()
                    self._fly_pair(item) if isinstance(item, Comparison) else self._fly(item)
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
        """Do one command and answer its future. Inside a live episode it may raise _Unwind (after answering)."""
        handler = getattr(self, "_do_" + type(command).__name__)
        self._origin = command.origin
        try:
            result = handler(command)
        except _Unwind:
            raise
        except RunnerError as e:
            command.future.set_exception(e)
        except Exception as e:  # noqa: BLE001 - never let a bad request kill the runner
            log.error("command %s failed:\n%s", command, traceback.format_exc())
            command.future.set_exception(RunnerError(f"{type(e).__name__}: {e}"))
        else:
            if not command.future.done():
                command.future.set_result(result)

    # -- checkpoints ------------------------------------------------------------------------------------------
    def _path_of(self, ref: str) -> Path:
        """A bare name is a folder under checkpoints_root (unless only ./name is a checkpoint) or an extra
        checkpoint's name; else a path, which must lie under checkpoints_root or be one this dashboard was started
        with or offers (`_offered`): a request cannot point it at any folder of the machine, and the refusal says
        the same whether the folder exists or not."""
        if not ref.strip():
            raise RunnerError("checkpoint is empty: name one (e.g. gsmn, table2/no-ground, run-3), or leave it out "
                              "for the default")
        extra = self.extra_checkpoints() if self.extra_checkpoints else {}
        try:
            if ref in extra and not (self.checkpoints_root / ref).is_dir():
                return extra[ref]
            candidate = self.checkpoints_root / ref
            if "/" not in ref and (candidate.is_dir() or not (Path(ref) / "meta.json").is_file()):
                return candidate
            if (candidate / "meta.json").is_file() and not (Path(ref) / "meta.json").is_file():  # table2/x
                return candidate
        except OSError as e:  # e.g. a name too long for the file system
            raise RunnerError(f"no checkpoint at {ref}: {e.strerror or e}") from e
        if not self._offered(Path(ref)):
            raise RunnerError(f"checkpoint {ref!r} is not one this dashboard offers: name a checkpoint under "
                              f"checkpoints/ (e.g. gsmn, table2/no-ground) or a finished fine-tuning run (run-N)")
        return Path(ref)

    def _offered(self, path: Path) -> bool:
        """Under checkpoints_root, or the checkpoint the dashboard was started with, or one loaded or offered."""
        try:
            resolved = path.resolve()
            known = {Path(k) for k in self.models} | {p.resolve() for p in (
                self.extra_checkpoints() if self.extra_checkpoints else {}).values()}
            if self.default_ref is not None:
                known.add(Path(self.default_ref).resolve())
            return resolved.is_relative_to(self.checkpoints_root.resolve()) or resolved in known
        except (OSError, RuntimeError):
            return False

    def _load_default(self) -> None:
        if self.default_ref is None:
            self.checkpoint_message = "No checkpoint: the expert flies, and there are no model maps."
            return
        try:
            self.default_model = self._model(self.default_ref).path.resolve().as_posix()
            m = self.models[self.default_model]
            self.checkpoint_message = (f"Checkpoint {m.path} ({m.meta.get('kind')}, created "
                                       f"{m.meta.get('created', '?')}).")
        except RunnerError as e:
            if self.require_checkpoint:
                raise
            self.checkpoint_message = (f"No model loaded: {e}. The expert can still fly and every world can be "
                                       f"explored; train one (docs/training.md) or pass --checkpoint.")

    def _model(self, ref: str) -> LoadedModel:
        from gsmn.model.checkpoint import CheckpointError, load_checkpoint
        from gsmn.model.gsmn import GSMN
        from gsmn.model.policy import ModelPolicy

        path = self._path_of(ref)
        try:
            key = path.resolve().as_posix()
            found = path.is_dir()
        except OSError as e:
            raise RunnerError(f"no checkpoint at {path}: {e.strerror or e}") from e
        if key in self.models:
            return self.models[key]
        if not found:
            raise RunnerError(f"no checkpoint at {path}")
        try:
            model, config, vocabulary, meta = load_checkpoint(path)
        except CheckpointError as e:
            raise RunnerError(str(e)) from e
        if not isinstance(model, GSMN):
            raise RunnerError(f"checkpoint {path} holds a {model.kind!r} model; the dashboard shows GSMN's maps and "
                              f"needs a 'gsmn' or 'gsmn-no-plan' checkpoint")
        cam = self.config.camera
        if model.image_size != (cam.width, cam.height):
            raise RunnerError(f"checkpoint {path} expects {model.image_size[0]}x{model.image_size[1]} images, the "
                              f"simulator renders {cam.width}x{cam.height}")
        name = path.name if path.parent.resolve() == self.checkpoints_root.resolve() else str(path)
        self.models[key] = LoadedModel(name, path, ModelPolicy(model, vocabulary, config), MapHeads.of(model), meta)
        return self.models[key]

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
                                    check_queue=not c.preempt)
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
                raise _Unwind
        else:
            self._pending.append(item)

    def _new_episode(self, env_id: int, text: str | None, policy: str, checkpoint: str | None,
                     paused: bool = False, check_queue: bool = False) -> Episode:
        """A checked episode (and, with `check_queue`, room for it in the queue), not yet stored or queued."""
        self._check_env_id(env_id)
        c = StartEpisode(env_id, text, policy, checkpoint, paused=paused)
        if c.policy not in POLICIES:
            raise RunnerError(f"policy must be one of {', '.join(POLICIES)}, got {c.policy!r}")
        model: LoadedModel | None
        if c.checkpoint is not None:
            model = self._model(c.checkpoint)
        elif self.default_model is not None:
            model = self.models[self.default_model]
        else:
            model = None
        if c.policy != "expert" and model is None:
            raise Conflict(f"no checkpoint to fly: {self.checkpoint_message} Choose the expert, or name a "
                           f"checkpoint.")
        if check_queue:
            self._check_queue()
        world = world_for_env(int(c.env_id), self.config.world)
        if c.instruction is None or not c.instruction.strip():
            try:
                task = task_for_env(int(c.env_id), self.config)
            except DemoPathError as e:
                raise RunnerError(f"environment {c.env_id} has no instruction with a demonstration path ({e})") from e
        else:
            try:
                instruction = parse_instruction(c.instruction, world)
            except InstructionError as e:
                raise RunnerError(str(e)) from e
            try:
                task = Task(world, instruction, demonstration_path(world, instruction.goal, self.config.expert))
            except DemoPathError as e:
                if c.policy == "expert":
                    raise RunnerError(f"the expert has no path to that goal ({e}); try another side") from e
                task = _straight_task(world, instruction, self.config.expert.waypoint_spacing)
        episode = Episode(id=self.episodes.new_id(), task=task, policy=c.policy,
                          system=model.policy.name if c.policy != "expert" else ExpertPolicy.name,
                          checkpoint=model.path.resolve().as_posix() if model else None,
                          horizon=self.config.task.horizon, start_paused=c.paused, origin=self._origin,
                          typed=c.instruction.strip() if c.instruction and c.instruction.strip() else None)
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
        raise _Unwind

    def _do_CancelEpisode(self, c: CancelEpisode) -> Episode:
        """Drop a queued episode, or end the live one."""
        episode = self.episodes.get(c.episode_id)
        if episode is None:
            raise NotFound(self.episodes.missing(c.episode_id))
        pair = self._pending_pair(episode)
        if episode in self._pending or pair is not None:
            self._pending.remove(pair or episode)
            for e in pair.episodes if pair else (episode,):
                e.status = CANCELLED
                self._notify("on_episode_end", e)
            return episode
        if episode is not self.live and not self._flying_in_pair(episode):
            raise Conflict(f"episode {episode.id} is {episode.status}: nothing to cancel")
        c.future.set_result(episode)
        raise _Unwind

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
        try:
            instruction = parse_instruction(c.text, episode.task.world)
        except InstructionError as e:
            raise RunnerError(str(e)) from e
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
        from gsmn.model.policy import ModelPolicy

        model = self.models.get(episode.checkpoint) if episode.checkpoint else None
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
            expert = ExpertPolicy(self.config)
            policy = WatchedPolicy(expert, watcher) if watcher is not None else expert
            carrier = watcher
        return Flight(episode, policy, watcher, carrier, expert)

    def _start(self, flight: Flight) -> RolloutStart | None:
        """None for an episode from the start corner; a fork is put at its step (`gsmn.task.fork`)."""
        episode, fork = flight.episode, flight.episode.fork
        episode.snapshots = FlightSnapshots()
        if fork is None:
            return None
        from gsmn.task.fork import fork_start

        world = episode.task.world
        self.env.reset(world.env_id, episode.instruction, world)
        flight.policy.reset(episode.task)
        if flight.expert is not None and fork.expert_task is not None:  # its path: the original's, or from the fork
            if not fork.same_expert and fork.step > 0:  # already in flight: no take-off ramp on its new path
                from dataclasses import replace

                flight.expert.config = replace(self.config, expert=replace(self.config.expert, ramp_waypoints=0))
            flight.expert.reset(fork.expert_task)
        start = fork_start(self.env, fork.snapshots, fork.step, fork.prefix, flight.carrier, fork.same_model,
                           flight.expert, fork.same_expert)
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
        except _Unwind:
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
                            maps=_step_maps(watcher) if watcher is not None else None,
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
                raise _Unwind
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
                raise _Unwind
            self._handle(command)
        self._last_step = time.perf_counter()


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


def _step_maps(policy) -> StepMaps | None:
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


def _replace_seconds(g: Grounding, seconds: float) -> Grounding:
    from dataclasses import replace

    return replace(g, seconds=seconds)
