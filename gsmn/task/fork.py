"""Forking an episode at step t: fly on from the exact state it was in at step t, with the same or another
instruction or policy (the dashboard's "fork", `POST /api/episodes/{id}/fork`).

The state at step t is the simulator's (`Env.get_state`: MuJoCo's integration state, 0.8 kB) and what the policy
carries into step t: a model's semantic map and its pose-noise generator (`ModelPolicy.carried`, 128 kB float32 at
the paper's sizes, twice that for a mirror ensemble), and the expert's progress along its path (one number). What
the instruction makes at reset (the sentence embedding and the language kernels) is not carried: the fork's
`reset` makes them for its own instruction.

`FlightSnapshots` keeps the simulator's state at every step and the policy's carried state every `every` steps
(keyframes). To stand at step t, `fork_start` restores the keyframe at or before t and replays the steps between:
it puts the simulator back at each of them, renders the same image, and lets the policy act on it (the action is
discarded), which rebuilds the semantic map exactly, since perception does not depend on the instruction. A fork
with another model, whose map the flight never held, replays every step from 0 the same way, so its map is the one
it would have built along the original's path. With `every=5` a fork replays at most 4 steps of the same model
(each a render and a model step, about 25 ms on these cores); the snapshots of a 150-step episode take about 4 MB
(docs/compare.md, "Forks").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gsmn.task.rollout import RolloutStart
from gsmn.world.env import Env, EnvState

KEYFRAME_EVERY = 5  # every 10 halved the memory, but a fork then replayed up to 9 steps: 0.6 s with the page open


@dataclass
class FlightSnapshots:
    """Per-step snapshots of one flight, appended by `record` after the policy acted at each step."""

    every: int = KEYFRAME_EVERY
    states: list[EnvState] = field(default_factory=list)  # at observation t, before its action was flown
    carried: dict[int, Any] = field(default_factory=dict)  # step j -> the model's carried state before acting at j
    progress: dict[int, float] = field(default_factory=dict)  # step t -> the expert's progress after acting at t

    def record(self, env: Env, model: Any | None, expert: Any | None) -> None:
        """Call once per step, after the policy acted on the observation `env` stands at. `model`: the part of the
        policy with a carried state (a ModelPolicy or Ensemble), `expert`: an ExpertPolicy, either may be None."""
        t = len(self.states)
        self.states.append(env.get_state())
        if model is not None and (t + 1) % self.every == 0:
            self.carried[t + 1] = model.carried()
        if expert is not None:
            self.progress[t] = float(expert.expert.progress)

    def prefix(self, t: int, with_carried: bool) -> FlightSnapshots:
        """The snapshots of steps 0..t-1 (a fork's own history); the keyframes only if the fork flies the same
        model."""
        return FlightSnapshots(self.every, list(self.states[:t]),
                               {j: c for j, c in self.carried.items() if j <= t} if with_carried else {},
                               {j: p for j, p in self.progress.items() if j < t})

    def has_expert_progress(self, t: int) -> bool:
        """Whether the expert's progress before acting at step t was recorded (an expert flew step t - 1)."""
        return t == 0 or t - 1 in self.progress

    def expert_progress_before(self, t: int) -> float:
        return self.progress[t - 1] if t > 0 else 0.0

    def nbytes(self) -> int:
        """Memory the snapshots hold (arrays and tensors)."""
        total = sum(s.physics.nbytes for s in self.states) + 8 * len(self.progress)
        return total + sum(_nbytes(c) for c in self.carried.values())


def _nbytes(x: Any) -> int:
    if isinstance(x, np.ndarray):
        return x.nbytes
    if hasattr(x, "element_size") and hasattr(x, "numel"):  # a torch tensor
        return x.element_size() * x.numel()
    if isinstance(x, tuple | list):
        return sum(_nbytes(v) for v in x)
    return 0


@dataclass(frozen=True)
class Prefix:
    """Steps 0..t-1 of the original as the fork's rollout continues them (EpisodeRecord's per-step fields)."""

    trajectory: tuple[tuple[float, float, float, float], ...]
    actions: tuple[tuple[float, float, bool], ...]
    stop_probabilities: tuple[float | None, ...]
    member_stop_probabilities: tuple[tuple[float, ...] | None, ...]


def fork_start(env: Env, snapshots: FlightSnapshots, t: int, prefix: Prefix, model: Any | None, same_model: bool,
               expert: Any | None, same_expert: bool, world: Any | None = None) -> RolloutStart:
    """Put `env` and a policy already `reset` for the fork's task at step t of the flight `snapshots` recorded.

    `model`: the fork's part with a carried state (or None); `same_model`: it is the network (and the kind: plain or
    mirror ensemble) that flew, so its keyframes apply; else its state is rebuilt from step 0. `expert`: the fork's
    ExpertPolicy (or None); `same_expert`: it follows the original expert's path, so its progress is restored (an
    expert with a new path starts on it at 0). `world`: the fork's world where it differs from the flight's (world
    edits at step t, gsmn.task.edits): `env` holds the flight's world, in which the model's memory of steps before
    t is rebuilt; then the drone is put at step t in `world` (the landmarks are static, so the simulator's state is
    the drone's alone and carries over)."""
    if not 0 <= t < len(snapshots.states):
        raise ValueError(f"step {t} is not recorded: the flight has steps 0 to {len(snapshots.states) - 1}")
    if len(prefix.trajectory) != t:
        raise ValueError(f"the prefix has {len(prefix.trajectory)} steps, a fork at step {t} needs {t}")
    if model is not None:
        k = 0
        if same_model:
            k = max((j for j in snapshots.carried if j <= t), default=0)
            if k > 0:
                model.restore(snapshots.carried[k])
        for j in range(k, t):
            model.act(env.set_state(snapshots.states[j]))
    if expert is not None and same_expert:
        expert.expert.progress = snapshots.expert_progress_before(t)
    obs = env.set_state(snapshots.states[t])
    if world is not None and world != env.world:
        obs = env.move_to(world)
    return RolloutStart(obs, prefix.trajectory, prefix.actions, prefix.stop_probabilities,
                        prefix.member_stop_probabilities)
