"""World edits (interventions on the world): move, remove or add a landmark, then fly the same instruction in the
edited world.

    edits = parse_edits([{"op": "move", "landmark": 3, "x": 12.0, "y": 20.5}, {"op": "remove", "landmark": 5},
                         {"op": "add", "noun_phrase": "tank", "x": 4.0, "y": 9.0}])
    task = edited_task(task_for_env(env_id, config), edits, config)

Landmarks are named by their index in the world *before* the edits (the indices the page and the API show), and the
edits apply in order. Everything downstream reads the edited `WorldSpec` the task carries: the simulator builds its
scene from it (gsmn.world.env.Env.reset takes the world), the expert follows the demonstration planned in it, and the
instruction's goal, the metrics, the ground truth and the attribution read its landmarks. The instruction keeps its
words: its landmark is the one it named (followed to wherever it was moved; refused if it was removed), its goal is
recomputed on the same side of it as seen from the start, and whether it is ambiguous is counted again.

An edit that cannot stand is refused with a message (`EditError`): a landmark put off the field (centres keep the
world generator's edge margin), onto the drone (closer than the landmark's radius plus the generator's start
clearance, from where the drone is: the start, or its position at a fork's step), onto another landmark (closer than
their radii plus the generator's gap), an index the world does not have, a noun phrase the catalogue does not have,
or an edit that leaves the instruction without its landmark or the demonstration without a path.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from gsmn.config import RunConfig
from gsmn.task.demo import DemoPathError, demonstration_path
from gsmn.task.instructions import InstructionError, goal_position
from gsmn.task.rollout import Task
from gsmn.world.catalogue import CATALOGUE
from gsmn.world.spec import LandmarkSpec, WorldSpec

OPS = ("move", "remove", "add")
MAX_EDITS = 32


class EditError(ValueError):
    """An edit that cannot stand; the message says which and why."""


@dataclass(frozen=True)
class WorldEdit:
    op: str  # move, remove, add
    landmark: int | None = None  # move, remove: its index in the world before the edits
    x: float | None = None  # move, add: where its centre goes (m)
    y: float | None = None
    noun_phrase: str | None = None  # add: which landmark of the catalogue
    yaw: float = 0.0  # add: its heading (rad)

    def to_dict(self) -> dict[str, Any]:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None and not (k == "yaw" and v == 0.0)}


def parse_edits(items: Sequence[Mapping[str, Any]]) -> tuple[WorldEdit, ...]:
    """Edits from their JSON form (the API's `world_edits`), checked for shape; EditError names the bad one."""
    if len(items) > MAX_EDITS:
        raise EditError(f"at most {MAX_EDITS} world edits, got {len(items)}")
    out = []
    for k, item in enumerate(items):
        where = f"world edit {k + 1}"
        op = item.get("op")
        if op not in OPS:
            raise EditError(f"{where}: op must be one of {', '.join(OPS)}, got {op!r}")
        needs = {"move": ("landmark", "x", "y"), "remove": ("landmark",), "add": ("noun_phrase", "x", "y")}[op]
        allowed = set(needs) | {"op"} | ({"yaw"} if op == "add" else set())
        missing, extra = [n for n in needs if item.get(n) is None], sorted(set(item) - allowed)
        problems = ([f"needs {', '.join(missing)}"] if missing else []) + (
            [f"takes no {', '.join(extra)}"] if extra else [])
        if problems:
            raise EditError(f"{where} ({op}): " + "; ".join(problems))
        try:
            edit = WorldEdit(op, None if item.get("landmark") is None else _index(item["landmark"]),
                             *(None if item.get(n) is None else _number(item[n], n) for n in ("x", "y")),
                             item.get("noun_phrase"), _number(item.get("yaw", 0.0), "yaw"))
        except (TypeError, ValueError) as e:
            raise EditError(f"{where} ({op}): {e}") from None
        out.append(edit)
    return tuple(out)


def _index(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"landmark must be an index (an integer >= 0), got {value!r}")
    return value


def _number(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def edit_world(world: WorldSpec, edits: Sequence[WorldEdit], config: RunConfig,
               drone_xy: tuple[float, float] | None = None, check: bool = True) -> tuple[WorldSpec, list[int | None]]:
    """The world after the edits, and for each landmark of the original world its index in the edited one (None:
    removed). `drone_xy`: where the drone is (default: the start). `check` False: edits made before (an episode read
    back) are made again without checking where they put the landmarks, which was checked when they were made."""
    drone = drone_xy if drone_xy is not None else (world.start_x, world.start_y)
    landmarks: list[LandmarkSpec | None] = list(world.landmarks)
    added: list[LandmarkSpec] = []
    for k, edit in enumerate(edits):
        where = f"world edit {k + 1} ({edit.op})"
        if edit.op in ("move", "remove"):
            if edit.landmark is None or edit.landmark >= len(landmarks) or landmarks[edit.landmark] is None:
                what = "was removed by an earlier edit" if edit.landmark is not None and \
                    edit.landmark < len(landmarks) else f"is not one of this world's {len(world.landmarks)} (0-" \
                                                        f"{len(world.landmarks) - 1})"
                raise EditError(f"{where}: landmark {edit.landmark} {what}")
            if edit.op == "remove":
                landmarks[edit.landmark] = None
                continue
            landmarks[edit.landmark] = dataclasses.replace(landmarks[edit.landmark], x=edit.x, y=edit.y)
        else:
            found = [i for i, c in enumerate(CATALOGUE) if c.noun_phrase == edit.noun_phrase]
            if not found:
                raise EditError(f"{where}: no landmark called {edit.noun_phrase!r} in the catalogue")
            model = CATALOGUE[found[0]]
            added.append(LandmarkSpec(model=model.name, noun_phrase=model.noun_phrase, class_id=found[0], x=edit.x,
                                      y=edit.y, yaw=edit.yaw, scale=1.0, radius=model.radius))
    kept = [lm for lm in landmarks if lm is not None] + added
    moved = {k for k, lm in enumerate(landmarks) if lm is not None and lm != world.landmarks[k]}
    if check:
        _check_places(kept, [lm for k, lm in enumerate(landmarks) if k in moved] + added, world, config, drone)
    index, n = [], 0
    for lm in landmarks:
        index.append(None if lm is None else n)
        n += lm is not None
    return dataclasses.replace(world, landmarks=tuple(kept)), index


def _check_places(landmarks: list[LandmarkSpec], placed: list[LandmarkSpec], world: WorldSpec, config: RunConfig,
                  drone) -> None:
    """The landmarks `placed` (moved or added) against the field, the drone and every other landmark kept (the
    world generator's rules; the landmarks left where they were stand as it placed them)."""
    c = config.world
    lo, hi = c.edge_margin, world.field_size - c.edge_margin
    if not landmarks:
        raise EditError("the edits leave the world without a landmark")
    for lm in placed:
        if not (lo <= lm.x <= hi and lo <= lm.y <= hi):
            raise EditError(f"the {lm.noun_phrase} at ({lm.x:.1f}, {lm.y:.1f}) would be off the field: centres stay "
                            f"within {lo:g}-{hi:g} m")
        if math.dist((lm.x, lm.y), drone) < lm.radius + c.start_clearance:
            raise EditError(f"the {lm.noun_phrase} at ({lm.x:.1f}, {lm.y:.1f}) would stand on the drone at "
                            f"({drone[0]:.1f}, {drone[1]:.1f}): keep it {lm.radius + c.start_clearance:.1f} m away")
        for other in landmarks:
            if other is not lm and math.dist((lm.x, lm.y), (other.x, other.y)) < lm.radius + other.radius + \
                    c.landmark_gap:
                raise EditError(f"the {lm.noun_phrase} at ({lm.x:.1f}, {lm.y:.1f}) would overlap the "
                                f"{other.noun_phrase} at ({other.x:.1f}, {other.y:.1f})")


def edited_task(task: Task, edits: Sequence[WorldEdit], config: RunConfig,
                drone_xy: tuple[float, float] | None = None) -> Task:
    """The task's instruction in its world after the edits (see the module docstring); the task itself without
    edits."""
    if not edits:
        return task
    world, index = edit_world(task.world, edits, config, drone_xy)
    i = task.instruction
    named = index[i.landmark_index]
    if named is None:
        raise EditError(f"the instruction names the {i.noun_phrase} (landmark {i.landmark_index}), which the edits "
                        "remove: fly another instruction, or keep that landmark")
    try:
        goal = goal_position(world, named, i.side)
    except InstructionError as e:
        raise EditError(str(e)) from None
    instruction = dataclasses.replace(i, landmark_index=named, goal_x=float(goal[0]), goal_y=float(goal[1]),
                                      ambiguous=len(world.landmarks_named(i.noun_phrase)) > 1)
    if not world.on_field(goal):
        raise EditError(f"the goal, the {i.side} side of the {i.noun_phrase}, would be off the field at "
                        f"({goal[0]:.1f}, {goal[1]:.1f})")
    try:
        path = demonstration_path(world, goal, config.expert)
    except DemoPathError as e:
        raise EditError(f"no demonstration in the edited world: {e}") from None
    return Task(world, instruction, path)


def edits_from_text(text: str, world: WorldSpec) -> tuple[WorldEdit, ...]:
    """Edits typed in a few words, `;`-separated: "move pumpkin to 12 20.5; remove box; add tank at 4 9". A landmark
    is named by its noun phrase (or its index, as in the API); a name that several landmarks share takes the index.
    EditError says what could not be read."""
    items: list[dict[str, Any]] = []
    for k, part in enumerate(p.strip() for p in text.split(";")):
        if not part:
            continue
        words = part.replace(",", " ").split()
        op, rest = words[0].lower(), words[1:]
        where = f"edit {k + 1} ({part!r})"
        try:
            if op == "remove" and rest:
                items.append({"op": "remove", "landmark": _landmark(" ".join(rest), world)})
            elif op in ("move", "add") and len(rest) >= 3 and rest[-3].lower() in ("to", "at"):
                x, y = float(rest[-2]), float(rest[-1])
                name = " ".join(rest[:-3])
                items.append({"op": "move", "landmark": _landmark(name, world), "x": x, "y": y} if op == "move" else
                             {"op": "add", "noun_phrase": name.lower(), "x": x, "y": y})
            else:
                raise ValueError("write 'move NAME to X Y', 'remove NAME' or 'add NAME at X Y'")
        except ValueError as e:
            raise EditError(f"{where}: {e}") from None
    return parse_edits(items)


def _landmark(name: str, world: WorldSpec) -> int:
    if name.strip().isdigit():
        return int(name)
    found = [i for i, lm in enumerate(world.landmarks) if lm.noun_phrase == name.strip().lower()]
    if len(found) == 1:
        return found[0]
    if not found:
        raise ValueError(f"no {name.strip()} in this world (its landmarks: "
                         f"{', '.join(lm.noun_phrase for lm in world.landmarks)})")
    raise ValueError(f"{len(found)} landmarks are called {name.strip()}: name one by its index "
                     f"({', '.join(map(str, found))})")
