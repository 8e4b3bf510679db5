"""The environment every later part uses: reset to an environment id, step with an action, observe.

An observation is the forward camera image plus the exact pose: the drone's position and heading, the
camera pose T_world_camera (computer-vision convention, see gsmn.world.sim) and intrinsics K, which the
model's ground projection needs. Stepping is deterministic for a given environment id and action
sequence. Actions are in SI units and clipped to the drone's limits (1.6 m/s, 2.44 rad/s, no reversing);
STOP is the task's business (gsmn.task), not the simulator's.

The simulator (MuJoCo) and the landmark assets load when an `Env` is made, not when this module is imported: the
model and the policies use the observation types without the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from gsmn.config import RunConfig
from gsmn.world.spec import WorldSpec, world_for_env

if TYPE_CHECKING:
    from gsmn.world.assets import AssetModel
    from gsmn.world.sim import Simulator


@dataclass(frozen=True)
class Action:
    forward_velocity: float  # m/s, clipped to [0, max_forward_velocity]
    yaw_rate: float  # rad/s, positive turns left (counter-clockwise seen from above)


@dataclass(frozen=True)
class Pose:
    position: np.ndarray  # (3,) world frame, metres
    yaw: float  # heading, rad, counter-clockwise from +x
    R_world_body: np.ndarray  # (3, 3)


@dataclass(frozen=True)
class Observation:
    image: np.ndarray | None  # (H, W, 3) uint8, top row first; None from an Env made with render=False
    pose: Pose
    T_world_camera: np.ndarray  # (4, 4), camera x right, y down, z forward
    K: np.ndarray  # (3, 3)
    step: int  # actions taken since reset
    time: float  # simulated seconds since reset


@dataclass(frozen=True)
class EnvState:
    """Everything an `Env` needs to fly on exactly as it did from one observation (`Env.get_state`)."""

    env_id: int
    step: int  # actions taken since reset
    physics: np.ndarray  # the simulator's integration state (float64, `Simulator.get_state`)


class Env:
    """A quadcopter in a procedurally generated world. Reuses the compiled world when reset to the same id.

    `render=False` skips the camera (observations carry the pose only), for policies that do not look,
    such as the expert and the trivial baselines."""

    def __init__(self, config: RunConfig | None = None, catalogue: tuple[AssetModel, ...] | None = None,
                 render: bool = True):
        from gsmn.world.assets import load_catalogue

        self.config = config or RunConfig()
        self.catalogue = catalogue or load_catalogue()
        self.render = render
        self.sim: Simulator | None = None
        self.instruction: str | None = None
        self._step = 0

    @property
    def world(self) -> WorldSpec:
        if self.sim is None:
            raise RuntimeError("call Env.reset(env_id) before using the environment")
        return self.sim.world

    def reset(self, env_id: int, instruction: str | None = None, world: WorldSpec | None = None
              ) -> Observation:
        """Start an episode in environment `env_id` (or in an explicit `world`) at its start corner."""
        from gsmn.world.sim import Simulator

        world = world or world_for_env(env_id, self.config.world)
        if self.sim is None or self.sim.world != world:
            if self.sim is not None:
                self.sim.close()
            self.sim = Simulator(world, self.config, self.catalogue)
        else:
            self.sim.reset()
        self.instruction = instruction
        self._step = 0
        return self.observe()

    def step(self, action: Action) -> Observation:
        if self.sim is None:
            raise RuntimeError("call Env.reset(env_id) before Env.step")
        self.sim.step(action.forward_velocity, action.yaw_rate)
        self._step += 1
        return self.observe()

    def get_state(self) -> EnvState:
        """The state at the current observation: `set_state` with it, and the same actions fly the same steps."""
        if self.sim is None:
            raise RuntimeError("call Env.reset(env_id) before Env.get_state")
        return EnvState(self.sim.world.env_id, self._step, self.sim.get_state())

    def set_state(self, state: EnvState) -> Observation:
        """Return to a state from `get_state` of this world (reset to it first) and observe there."""
        self.restore(state)
        return self.observe()

    def restore(self, state: EnvState) -> None:
        """`set_state` without the observation (no image rendered): for a caller that steps on at once."""
        if self.sim is None or self.sim.world.env_id != state.env_id:
            raise RuntimeError(f"the state is of environment {state.env_id}; reset the Env to it first")
        self.sim.set_state(state.physics)
        self._step = state.step

    def move_to(self, world: WorldSpec) -> Observation:
        """The drone, as it is, in another world of the same environment (its landmarks edited: gsmn.task.edits),
        at the same step; observed there."""
        from gsmn.world.sim import Simulator

        assert self.sim is not None
        drone, step = self.sim.drone_state(), self._step
        self.sim.close()
        self.sim = Simulator(world, self.config, self.catalogue)
        self.sim.set_drone_state(drone)
        self._step = step
        return self.observe()

    def observe(self) -> Observation:
        sim = self.sim
        assert sim is not None
        R = sim.R_world_body
        pose = Pose(position=sim.position, yaw=sim.yaw, R_world_body=R)
        image = sim.render() if self.render else None
        return Observation(image=image, pose=pose, T_world_camera=sim.T_world_camera, K=sim.K.copy(), step=self._step,
                           time=sim.time)

    def close(self) -> None:
        if self.sim is not None:
            self.sim.close()
            self.sim = None

    def __enter__(self) -> Env:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
