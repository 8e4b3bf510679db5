"""How an episode is kept in the SQLite record (`app.jobs.db`, tables kept_episodes and kept_steps) and read back:
its row, its steps, and `KeptStore`, the runner's episode store over the record. What writes them as the episode
flies, and the retention limit: `app.jobs.kept`.

- **Compact.** Per step: the pose, the actions and P(stop) as a small JSON object, the camera image as the JPEG
  the page already sends, and the model's maps quantised to 8 bits per channel (each channel's own minimum and
  maximum kept as float32 beside it, so a value comes back within 1/510 of its channel's range), zlib-compressed.
- **Read back as episodes.** `KeptStore` is the runner's episode store: an episode no longer in memory is loaded
  from the record on demand (maps back as float16), so the API's routes and the page's replay work on it as on
  one just flown.
"""

from __future__ import annotations

import io
import json
from collections import OrderedDict
from dataclasses import asdict
from typing import Any

import numpy as np

from app.jobs.db import Database
from app.live.recording import Episode, EpisodeResult, EpisodeStore, StepMaps, StepRecord
from gsmn.config import RunConfig, WorldConfig
from gsmn.task.edits import edit_world, parse_edits
from gsmn.task.instructions import Instruction
from gsmn.task.rollout import Task
from gsmn.world.spec import world_for_env


# -- compact steps ------------------------------------------------------------------------------------------------
def pack_maps(maps: dict[str, np.ndarray]) -> bytes:
    """The maps (each channels first) quantised to uint8 per channel with each channel's float32 range, in one
    compressed .npz."""
    arrays: dict[str, np.ndarray] = {}
    for name, m in maps.items():
        a = np.asarray(m, np.float32)
        flat = a.reshape(a.shape[0], -1) if a.ndim >= 2 else a.reshape(1, -1)
        lo, hi = flat.min(axis=1), flat.max(axis=1)
        scale = np.where(hi > lo, hi - lo, 1.0)
        q = np.round((flat - lo[:, None]) / scale[:, None] * 255.0).astype(np.uint8)
        arrays[f"{name}.q"] = q.reshape(a.shape)
        arrays[f"{name}.range"] = np.stack([lo, hi]).astype(np.float32)
    out = io.BytesIO()
    np.savez_compressed(out, **arrays)
    return out.getvalue()


def unpack_maps(blob: bytes) -> dict[str, np.ndarray]:
    """The maps of `pack_maps`, back as float16."""
    with np.load(io.BytesIO(blob)) as z:
        names = sorted({k.rsplit(".", 1)[0] for k in z.files})
        out = {}
        for name in names:
            q, (lo, hi) = z[f"{name}.q"], z[f"{name}.range"]
            flat = q.reshape(q.shape[0], -1) if q.ndim >= 2 else q.reshape(1, -1)
            values = lo[:, None] + flat.astype(np.float32) / 255.0 * (hi - lo)[:, None]
            out[name] = values.reshape(q.shape).astype(np.float16)
    return out


def step_row(record: StepRecord) -> tuple[int, str, bytes, bytes | None]:
    m = record.maps
    data = {"time": record.time, "position": list(record.position), "yaw": record.yaw,
            "T_world_camera": np.asarray(record.T_world_camera, np.float32).round(6).tolist(), "v": record.v,
            "omega": record.omega, "stop": record.stop, "stop_probability": record.stop_probability,
            "model": None if m is None else {"pose": np.asarray(m.pose, np.float32).tolist(), "v": m.v,
                                             "omega": m.omega, "stop_probability": m.stop_probability}}
    return record.step, json.dumps(data), record.camera_jpeg, pack_maps(m.maps) if m is not None else None


def step_of_row(row, where: str = "the record") -> StepRecord:
    """A kept step. Maps whose bytes were damaged in the record (SQLite's own checks cannot see inside a blob) come
    back as none, with `damaged` saying so, so the rest of the episode still reads."""
    d = json.loads(row["data"])
    model = d["model"]
    maps, damaged = None, None
    if model is not None and row["maps"] is not None:
        try:
            unpacked = unpack_maps(row["maps"])
        except Exception as e:  # noqa: BLE001 - zip, zlib and numpy each fail in their own way on damaged bytes
            damaged = (f"step {row['step']}'s maps are damaged in {where} and cannot be read ({type(e).__name__}: "
                       f"{e}); the episode's other steps read")
        else:
            maps = StepMaps(maps=unpacked, pose=np.array(model["pose"], np.float32), v=model["v"],
                            omega=model["omega"], stop_probability=model["stop_probability"])
    return StepRecord(step=int(row["step"]), time=d["time"], position=tuple(d["position"]), yaw=d["yaw"],
                      T_world_camera=np.array(d["T_world_camera"], np.float32), camera_jpeg=bytes(row["camera"]),
                      v=d["v"], omega=d["omega"], stop=d["stop"], maps=maps, stop_probability=d["stop_probability"],
                      damaged=damaged)


def task_json(task: Task, world_config: WorldConfig, typed: str | None = None, relation: dict | None = None,
              world_edits: tuple = ()) -> str:
    """The parsed instruction (the template flown) and the text typed, the demonstration path, and the world settings
    the world is drawn with (so that the episode reads back the same under a server, or `gsmn export`, started with
    other settings), with the edits made to it (gsmn.task.edits); and `relation` (`episode_relation`): where a fork
    starts, which side of a comparison."""
    return json.dumps({"instruction": asdict(task.instruction), "typed": typed,
                       "path": np.asarray(task.path).round(4).tolist(), "world": asdict(world_config),
                       **({"world_edits": [e.to_dict() for e in world_edits]} if world_edits else {}),
                       **(relation or {})})


def episode_relation(episode: Episode) -> dict[str, Any]:
    """What the task JSON says of an episode's relation to another: `fork` {episode_id, step} (steps 0..step-1 are
    that episode's), `comparison` {id, side, with} (the comparison's id in the server that flew it, 1 for the
    policy chosen first and 2 for the one compared with, and the other episode's id). Kept in the task JSON rather
    than in columns of their own: a record keeps its schema, and an older server still reads it (it ignores keys it
    does not know)."""
    out: dict[str, Any] = {}
    if episode.fork is not None:
        out["fork"] = {"episode_id": int(episode.fork.episode_id), "step": int(episode.fork.step)}
    if episode.intervention is not None:  # the map it flew with from the fork's step (gsmn.analysis.intervention)
        out["intervention"] = episode.intervention.to_dict()
    if episode.comparison is not None:
        out["comparison"] = {"id": int(episode.comparison), "side": episode.comparison_side,
                             "with": episode.compared_with}
    return out


def _intervention(d: dict | None):
    """A kept episode's map intervention, read back; one this code cannot read is left out, not fatal."""
    if d is None:
        return None
    from gsmn.analysis.intervention import InterventionError, parse_intervention

    try:
        return parse_intervention(d)
    except InterventionError:
        return None


# -- the record of episodes -----------------------------------------------------------------------------------------
class KeptStore(EpisodeStore):
    """The runner's episodes: those in memory (the last `limit` flown, and the live and queued ones) and every
    episode kept in the record, loaded on demand. Ids continue from the record's: never reused."""

    def __init__(self, db: Database, config: RunConfig, limit: int = 16, cache: int = 4):
        super().__init__(limit)
        self.db, self.config = db, config
        self._next_id = db.next_kept_id()
        self._loaded: OrderedDict[int, Episode] = OrderedDict()  # episodes read back from the record
        self._cache = cache

    def add(self, episode: Episode) -> None:
        """Accept an episode: its row goes into the record at once (queued), so its id is the record's from then on,
        never given again, and a server stopped before it flies keeps it as not flown. A record that cannot be
        written refuses it (RecordError, 503, naming the file)."""
        self.db.add_kept(kept_row(episode, self.config.world))
        super().add(episode)

    def get_in_memory(self, episode_id: int) -> Episode | None:
        return super().get(episode_id)

    def get(self, episode_id: int) -> Episode | None:
        episode = super().get(episode_id)
        if episode is not None:
            return episode
        with self._lock:
            if episode_id in self._loaded:
                self._loaded.move_to_end(episode_id)
                return self._loaded[episode_id]
        episode = self.load(episode_id)
        if episode is not None:
            with self._lock:
                self._loaded[episode_id] = episode
                while len(self._loaded) > self._cache:
                    self._loaded.popitem(last=False)
        return episode

    def load(self, episode_id: int) -> Episode | None:
        """The episode as the record holds it, or None when it was never kept or was removed."""
        row = self.db.kept(episode_id)
        if row is None:
            return None
        task = json.loads(row["task"])
        world_config = WorldConfig(**task["world"]) if "world" in task else self.config.world
        world = world_for_env(int(row["env_id"]), world_config)
        edits = parse_edits(task.get("world_edits", []))
        if edits:  # the world it flew: the same edits, made again
            world = edit_world(world, edits, RunConfig(world=world_config), check=False)[0]
        instruction = Instruction(**task["instruction"])
        episode = Episode(id=int(row["id"]), task=Task(world, instruction, np.array(task["path"], np.float64)),
                          policy=row["policy"], system=row["system"], checkpoint=row["checkpoint"],
                          horizon=int(row["horizon"]), status=row["status"], error=row["error"],
                          created=float(row["created"]), typed=task.get("typed"), world_edits=edits,
                          intervention=_intervention(task.get("intervention")))
        if row["result"] is not None:
            episode.result = EpisodeResult(**json.loads(row["result"]))
        episode.steps.extend(step_of_row(r, str(self.db.path)) for r in self.db.kept_steps(episode_id))
        return episode

    def missing(self, episode_id: int) -> str:
        if episode_id >= self._next_id:
            return f"no episode {episode_id}: none has that id yet"
        return (f"episode {episode_id} is no longer kept: it was removed from the record (the retention limit "
                f"removes the oldest unpinned episodes), or it never flew")

    def forget(self, episode_id: int) -> None:
        """Drop a removed episode from memory too."""
        with self._lock:
            self._loaded.pop(episode_id, None)
            episode = self._episodes.get(episode_id)
            if episode is not None and not episode.live:
                del self._episodes[episode_id]

    def pinned(self, episode_id: int) -> bool:
        row = self.db.kept(episode_id)
        return bool(row["pinned"]) if row is not None else False


def kept_row(episode: Episode, world_config: WorldConfig) -> dict[str, Any]:
    """An episode's row as it is accepted or starts flying (its steps' count, bytes and pin are the record's)."""
    world = episode.task.world
    return {"id": episode.id, "created": episode.created, "status": episode.status, "env_id": world.env_id,
            "split": world.split, "instruction": episode.instruction,
            "task": task_json(episode.task, world_config, episode.typed, episode_relation(episode),
                              episode.world_edits),
            "policy": episode.policy, "system": episode.system, "checkpoint": episode.checkpoint,
            "horizon": episode.horizon, "error": episode.error}
