"""Comparisons and forks: two policies flying one environment side by side, and an episode forked at step t.

**Two episodes stepping together.** The runner owns one `Env`. A comparison flies both episodes in that one
simulator, alternating: each round restores episode A's physics state (`Env.get_state`, 0.8 kB, restored with
`mj_setState` + `mj_forward`, microseconds), flies A's next step, saves its state, then does the same for B, then
answers commands once (pause, single step and the speed limit pace the pair, not each episode). Both episodes are
of the same world, so the compiled MuJoCo model, its textures and the renderer's GL context serve both; a second
`Env` would compile the world and open a second GL context for nothing, and a second thread would break the
runner's one-thread ownership of the simulator. Each rollout is `gsmn.task.rollout.rollout_steps`, the one rollout
function one step at a time, so a comparison's episodes are the episodes `POST /api/episodes` would fly.

**Forks.** `POST /api/episodes/{id}/fork` makes an episode whose steps 0..t-1 are the original's records and whose
flight starts at the original's exact state at step t (`gsmn.task.fork`): the fork's policy acts on the same
observation t, so with the same policy and instruction its step t is the original's too, and it ends as the
original did.

**Where they part** (`diverged_at`): the first step at which the two drones are more than 1 m apart, or at which
one says STOP (or has already ended) and the other does not; None while they have not parted.
"""

from __future__ import annotations

import logging
import time
import traceback
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from app.live.commands import POLICIES, Command, Conflict, NotFound, RunnerError
from app.live.flight import Flight, Unwind, intervention_maker, task_for_text
from app.live.recording import CANCELLED, FAILED, FINISHED, LIVE, PAUSED, RUNNING, Episode, EpisodeResult
from gsmn.task.demo import DemoPathError, demonstration_path, resample
from gsmn.task.edits import EditError, edit_world, edited_task
from gsmn.task.fork import FlightSnapshots, Prefix
from gsmn.task.rollout import Task, rollout_steps

log = logging.getLogger("gsmn.dashboard")
PART_DISTANCE = 1.0  # m: two drones further apart than this have parted
MAX_COMPARISONS = 32  # kept in memory, the oldest dropped


# -- commands -------------------------------------------------------------------------------------------------
@dataclass
class PolicySpec:
    policy: str = "model"
    checkpoint: str | None = None
    instruction: str | None = None  # None: the comparison's


@dataclass
class StartComparison(Command):
    env_id: int
    instruction: str | None  # None: the environment's own
    policies: list[PolicySpec]
    preempt: bool = False


@dataclass
class ForkEpisode(Command):
    episode_id: int
    step: int
    instruction: str | None = None  # None: the original's
    checkpoint: str | None = None  # None: the original's model
    policy: str | None = None  # None: the original's
    preempt: bool = False
    world_edits: tuple = ()  # gsmn.task.edits.WorldEdit made to the original's world at the fork's step
    intervention: Any = None  # gsmn.analysis.intervention.Intervention: the model flies on with this map


# -- records --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ForkPoint:
    """Where a fork starts: the original's flight snapshots, step t, and how much of its state applies."""

    episode_id: int
    step: int
    snapshots: FlightSnapshots
    prefix: Prefix
    same_model: bool  # the fork flies the model (and kind) that flew: its keyframes apply
    same_expert: bool  # the fork's expert follows the original expert's path: its progress applies
    expert_task: Task | None  # the path the fork's expert follows (from the fork point, for a new instruction)
    world: Any = None  # the original's world (gsmn.world.spec.WorldSpec), where the model's memory is rebuilt


@dataclass
class Comparison:
    id: int
    episodes: tuple[Episode, Episode]
    created: float = field(default_factory=time.time)

    @property
    def status(self) -> str:
        statuses = {e.status for e in self.episodes}
        for s in ("running", "paused", "queued", "failed", "cancelled"):
            if s in statuses:
                return s
        return "finished"

    def diverged_at(self) -> int | None:
        a, b = self.episodes
        return diverged_at([s.position for s in a.steps], [s.stop for s in a.steps], a.live,
                           [s.position for s in b.steps], [s.stop for s in b.steps], b.live)


def diverged_at(pos_a, stop_a, live_a: bool, pos_b, stop_b, live_b: bool,
                distance: float = PART_DISTANCE) -> int | None:
    """The first step at which two flights of one world part (see the module's docstring). `pos_*`: (x, y, ...) per
    recorded step, `stop_*`: whether that step said STOP, `live_*`: whether more steps may come."""
    n = min(len(pos_a), len(pos_b))
    for t in range(n):
        if float(np.hypot(pos_a[t][0] - pos_b[t][0], pos_a[t][1] - pos_b[t][1])) > distance:
            return t
        if stop_a[t] != stop_b[t]:
            return t
    if len(pos_a) != len(pos_b):  # the shorter one ended (horizon or STOP at n - 1 on both is not a part)
        shorter_live = live_a if len(pos_a) < len(pos_b) else live_b
        if not shorter_live:
            return n
    return None


# -- the runner's part ----------------------------------------------------------------------------------------
class Comparisons:
    """Comparisons and forks for `app.live.runner.Runner`, which holds one: their commands (the runner dispatches
    `StartComparison` and `ForkEpisode` to `do_*`) and the paired flight, all on the runner thread, with the
    runner's queue, simulator and step pacing."""

    def __init__(self, runner):
        self.runner = runner
        self.store: OrderedDict[int, Comparison] = OrderedDict()
        self.live: Comparison | None = None
        self._next = 1

    def pending_pair(self, episode: Episode) -> Comparison | None:
        return next((c for c in self.runner._pending if isinstance(c, Comparison) and episode in c.episodes), None)

    def flying(self, episode: Episode) -> bool:
        return self.live is not None and episode in self.live.episodes

    # -- commands ---------------------------------------------------------------------------------------------
    def do_StartComparison(self, c: StartComparison) -> Comparison:
        r = self.runner
        if len(c.policies) != 2:
            raise RunnerError(f"a comparison flies two policies, got {len(c.policies)}")
        if not c.preempt:
            r._check_queue()
        episodes = tuple(r._new_episode(c.env_id, spec.instruction or c.instruction, spec.policy,
                                        spec.checkpoint) for spec in c.policies)
        comparison = Comparison(self._next, episodes)
        self._next += 1
        for e, other in zip(episodes, episodes[::-1], strict=True):
            e.comparison, e.compared_with = comparison.id, other.id
            r.episodes.add(e)
        self.store[comparison.id] = comparison
        while len(self.store) > MAX_COMPARISONS:
            self.store.popitem(last=False)
        r._enqueue(c, comparison, comparison)
        return comparison

    def do_ForkEpisode(self, c: ForkEpisode) -> Episode:
        r = self.runner
        original, n = self._forkable(c.episode_id)
        if not 0 <= c.step < n:
            raise RunnerError(f"step {c.step} is not recorded: episode {original.id} has steps 0 to {n - 1}")
        policy = c.policy or original.policy
        if policy not in POLICIES:
            raise RunnerError(f"policy must be one of {', '.join(POLICIES)}, got {policy!r}")
        task = self._fork_task(original, c)
        checkpoint = c.checkpoint
        if checkpoint is None and original.checkpoint is not None and original.checkpoint in r.models:
            checkpoint = original.checkpoint
        # checked with the original's instruction (whose path exists); the fork's own task replaces it
        episode = r._new_episode(original.env_id, original.instruction, policy, checkpoint, check_queue=not c.preempt)
        episode.task, episode.world_edits = task, tuple(c.world_edits)
        episode.fork = self._fork_point(original, episode, c.step)
        if c.intervention is not None:
            episode.intervention = c.intervention
            episode.intervene = intervention_maker(r, c.intervention, policy, episode.checkpoint)
        episode.steps = list(original.steps[:c.step])
        r.episodes.add(episode)
        r._enqueue(c, episode, episode)
        return episode

    def _fork_task(self, original: Episode, c: ForkEpisode) -> Task:
        """The fork's task: the original's, or another instruction, in the original's world or with `c.world_edits`
        made to it at step t (a landmark may not be put on the drone where it is then)."""
        r, typed = self.runner, c.instruction is not None and c.instruction.strip() not in ("", original.instruction)
        if not c.world_edits:
            return task_for_text(original.task.world, c.instruction, r.config) if typed else original.task
        if original.world_edits:
            raise RunnerError(f"episode {original.id} flies an edited world already: fork an episode of the "
                              "environment's own world to edit it")
        s = original.steps[c.step]
        drone = (float(s.position[0]), float(s.position[1]))
        try:
            if typed:
                return task_for_text(edit_world(original.task.world, c.world_edits, r.config, drone)[0],
                                     c.instruction, r.config)
            return edited_task(original.task, c.world_edits, r.config, drone)
        except EditError as e:
            raise RunnerError(str(e)) from e

    def _forkable(self, episode_id: int) -> tuple[Episode, int]:
        """The episode to fork, and how many of its steps have a simulator state to start from."""
        episodes = self.runner.episodes
        original = episodes.get(episode_id)
        if original is None:
            raise NotFound(episodes.missing(episode_id))
        if original.live:
            raise Conflict(f"episode {original.id} is {original.status}: fork it once it has ended")
        snapshots: FlightSnapshots | None = original.snapshots
        n = min(len(original.steps), len(snapshots.states)) if snapshots is not None else 0
        if n == 0:
            raise Conflict(f"episode {original.id} has no recorded state to fork from: the simulator states a fork "
                           f"starts from are kept in memory only, so an episode kept from before a restart cannot be "
                           f"forked; fly it again and fork that")
        return original, n

    def _fork_point(self, original: Episode, episode: Episode, t: int) -> ForkPoint:
        """Where `episode` (a fork of `original` at step `t`) starts, and how much of the original's state applies."""
        policy, task, snapshots = episode.policy, episode.task, original.snapshots
        plain = ("model", "expert")  # the expert flies with the plain model watching
        same_model = (episode.checkpoint is not None and episode.checkpoint == original.checkpoint
                      and (policy == original.policy or (policy in plain and original.policy in plain)))
        expert_task, same_expert = None, False
        if policy == "expert":
            prior = original.fork.expert_task if original.fork is not None else None
            same_instruction = task.instruction.text == original.instruction and not episode.world_edits
            if same_instruction and original.policy == "expert" and snapshots.has_expert_progress(t):
                expert_task, same_expert = prior or original.task, True
            else:
                expert_task = _expert_task_from(original, t, task, self.runner.config)
        steps = original.steps[:t]
        prefix = Prefix(tuple((s.position[0], s.position[1], s.position[2], s.yaw) for s in steps),
                        tuple((s.v, s.omega, s.stop) for s in steps), tuple(s.stop_probability for s in steps),
                        tuple(None for _ in steps))
        return ForkPoint(original.id, t, snapshots, prefix, same_model, same_expert, expert_task, original.task.world)

    # -- flying a pair ----------------------------------------------------------------------------------------
    def fly(self, comparison: Comparison) -> None:
        """Fly a comparison's two episodes in the runner's one simulator, a step of each in turn."""
        r = self.runner
        flights: list[Flight] = [r._flight(e) for e in comparison.episodes]
        gens = [self._steps(f) for f in flights]
        states: list[Any] = [None, None]
        done = [False, False]
        self._begin(comparison, flights)
        try:
            while not all(done):
                for i, f in enumerate(flights):
                    if not done[i]:
                        done[i] = self._step(f, gens[i], states, i)
                if not all(done):
                    live = next(f.episode for f, d in zip(flights, done, strict=True) if not d)
                    r._between_steps(live)
                    for f, d in zip(flights, done, strict=True):  # pause and resume show on both
                        if not d:
                            f.episode.status = PAUSED if r.paused else RUNNING
        except Unwind:
            for f in flights:
                if f.episode.status in LIVE:
                    f.episode.status = CANCELLED
        finally:
            for g in gens:
                g.close()
            self._end(flights)

    def _steps(self, f: Flight):
        r = self.runner
        f.episode.snapshots = FlightSnapshots()
        return rollout_steps(r.env, f.policy, f.episode.task, f.episode.horizon,
                             on_step=lambda obs, action: r._on_step(f.episode, obs, action, f, pace=False),
                             success_radius=r.config.task.success_radius)

    def _begin(self, comparison: Comparison, flights: list[Flight]) -> None:
        r = self.runner
        r.live, self.live = comparison.episodes[0], comparison
        r.paused = comparison.episodes[0].start_paused
        r._step_budget = 0
        r._last_step = 0.0
        for f in flights:
            f.episode.status = PAUSED if r.paused else RUNNING
            f.episode.started = time.perf_counter()
            r._notify("on_episode_start", f.episode)

    def _step(self, f: Flight, gen, states: list[Any], i: int) -> bool:
        """One step of one of the pair, from its own simulator state; True when its episode has ended."""
        env = self.runner.env
        if states[i] is not None:
            env.restore(states[i])  # the step observes after it acts: no image of the restored state is needed
        try:
            next(gen)
            states[i] = env.get_state()
            return False
        except StopIteration as stop:
            last = f.episode.steps[-1] if f.episode.steps else None
            f.episode.result = EpisodeResult.of(stop.value, last.decisive_stop_probability if last else None)
            f.episode.status = FINISHED
        except Unwind:
            raise
        except Exception as e:  # noqa: BLE001 - one episode fails, the other flies on
            log.error("episode %d failed:\n%s", f.episode.id, traceback.format_exc())
            f.episode.status, f.episode.error = FAILED, f"{type(e).__name__}: {e}"
        f.episode.finished = time.perf_counter()
        return True

    def _end(self, flights: list[Flight]) -> None:
        r = self.runner
        for f in flights:
            if f.episode.finished is None:
                f.episode.finished = time.perf_counter()
        r.live, self.live = None, None
        r.paused = False
        for f in flights:
            r._notify("on_episode_end", f.episode)


def _expert_task_from(original: Episode, t: int, task: Task, config) -> Task:
    """The fork's expert path: from the drone's pose at step t to the fork's goal (the demonstration planner, with
    the world's start moved there), or straight there if the planner finds none."""
    s = original.steps[t]
    world = replace(task.world, start_x=float(s.position[0]), start_y=float(s.position[1]), start_yaw=float(s.yaw))
    try:
        path = demonstration_path(world, task.instruction.goal, config.expert)
    except DemoPathError:
        path = resample(np.stack([world.start_position, task.instruction.goal]), config.expert.waypoint_spacing)
    return Task(task.world, task.instruction, path)
