"""Instructions and their goals (paper: Data).

Each environment gets one instruction "go to the {side} side of the {noun phrase}": a landmark of the world
and one of four sides, both uniform, redrawn until the goal is more than 6 m (and less than 60 m) from the
start. The goal lies at the landmark's scaled radius on that side, where sides are taken as seen from the
start: with theta0 the direction from the landmark back toward the start,

    front = theta0, back = theta0 + pi, left = theta0 - pi/2, right = theta0 + pi/2.

Handedness: looking from the start at the landmark means facing theta0 + pi; the viewer's left is a
counter-clockwise quarter turn from there (x east, y north, z up), theta0 + 3pi/2 = theta0 - pi/2.
`gsmn.task.metrics.side_of` uses the same convention, so each goal sits on its quadrant's bisector.

Departures: the paper's figures write "... side of fir tree" without "the" before the noun phrase; we write
"the" and `parse_instruction` accepts either. We also redraw instructions whose goal lies outside the field
(`TaskConfig.goal_in_field`): their demonstration would leave the field, which the original rejects.

`parse_instruction` turns free text from the dashboard into an `Instruction` for a given world through
`gsmn.task.understand` (everyday phrasings read as the template, refusals meant for users).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from gsmn.config import TaskConfig
from gsmn.world.catalogue import NOUN_PHRASES
from gsmn.world.spec import WorldSpec

SIDES = ("left", "right", "front", "back")
TEMPLATE = "go to the {side} side of the {noun_phrase}"

# Angle of each side's goal relative to theta0 (direction from the landmark toward the start).
_SIDE_OFFSET = {"front": 0.0, "back": math.pi, "left": -math.pi / 2, "right": math.pi / 2}


class InstructionError(ValueError):
    """An instruction cannot be made or understood; the message is meant for users."""


@dataclass(frozen=True)
class Instruction:
    text: str
    landmark_index: int  # into world.landmarks
    noun_phrase: str
    side: str
    goal_x: float
    goal_y: float
    ambiguous: bool  # the noun phrase names more than one landmark of this world

    @property
    def goal(self) -> np.ndarray:
        return np.array([self.goal_x, self.goal_y])


def tokenize(text: str) -> list[str]:
    """Punctuation to spaces, lower case, split on whitespace (as the original)."""
    return re.sub(r"[^\w\s]|_", " ", text).lower().split()


VOCABULARY: tuple[str, ...] = tuple(sorted(
    set(tokenize(TEMPLATE.format(side="", noun_phrase=""))) | set(SIDES)
    | {w for phrase in NOUN_PHRASES for w in tokenize(phrase)}))


def goal_position(world: WorldSpec, landmark_index: int, side: str) -> np.ndarray:
    """The goal at the landmark's scaled radius on `side`, as seen from the start. Shape (2,)."""
    if side not in SIDES:
        raise InstructionError(f"unknown side {side!r}; choose from {', '.join(SIDES)}")
    lm = world.landmarks[landmark_index]
    theta0 = math.atan2(world.start_y - lm.y, world.start_x - lm.x)
    theta = theta0 + _SIDE_OFFSET[side]
    return np.array([lm.x + lm.radius * math.cos(theta), lm.y + lm.radius * math.sin(theta)])


def make_instruction(world: WorldSpec, landmark_index: int, side: str) -> Instruction:
    lm = world.landmarks[landmark_index]
    goal = goal_position(world, landmark_index, side)
    return Instruction(text=TEMPLATE.format(side=side, noun_phrase=lm.noun_phrase), landmark_index=landmark_index,
                       noun_phrase=lm.noun_phrase, side=side, goal_x=float(goal[0]), goal_y=float(goal[1]),
                       ambiguous=len(world.landmarks_named(lm.noun_phrase)) > 1)


def acceptable(world: WorldSpec, instruction: Instruction, config: TaskConfig) -> bool:
    """The sampling rule: 6 m < |goal - start| < 60 m (and, by default, the goal inside the field)."""
    d = math.dist((instruction.goal_x, instruction.goal_y), (world.start_x, world.start_y))
    inside = world.on_field((instruction.goal_x, instruction.goal_y))
    return config.min_goal_distance < d < config.max_goal_distance and (inside or not config.goal_in_field)


def sample_instruction(world: WorldSpec, rng: np.random.Generator, config: TaskConfig | None = None
                       ) -> Instruction:
    """Draw a landmark and a side uniformly until the goal is acceptable."""
    config = config or TaskConfig()
    for _ in range(config.instruction_draws):
        index = int(rng.integers(len(world.landmarks)))
        side = SIDES[int(rng.integers(len(SIDES)))]
        instruction = make_instruction(world, index, side)
        if acceptable(world, instruction, config):
            return instruction
    raise InstructionError(f"no acceptable instruction in environment {world.env_id} after "
                           f"{config.instruction_draws} draws")


def rng_for_instruction(env_id: int, seed: int = 0) -> np.random.Generator:
    """A stream apart from the world's (SeedSequence([seed, env_id]))."""
    return np.random.default_rng(np.random.SeedSequence([seed, env_id, 1]))


def instruction_for_env(world: WorldSpec, config: TaskConfig | None = None) -> Instruction:
    """The instruction of an environment: deterministic for (config.seed, world.env_id)."""
    config = config or TaskConfig()
    return sample_instruction(world, rng_for_instruction(world.env_id, config.seed), config)
