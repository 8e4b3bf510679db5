"""A compact on-disk store of episodes for training (paper: Learning; the datasets D of Algorithm 1).

One compressed `.npz` file per episode (images as uint8, camera poses, drone poses, expert labels, and
the world and instruction as JSON), written atomically, so a collection killed at any point leaves only
whole episodes and can resume by skipping the keys already present. Training reads episodes one at a
time; nothing holds the whole set in memory. Rendered frames compress about 19x (flat-shaded scenes):
an episode of 31 frames is about 0.18 MB and reads back in about 20 ms.

Loading never unpickles: arrays are plain numeric, strings are stored as JSON bytes.
"""

from __future__ import annotations

import json
import os
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from gsmn.model.batch import EpisodeSample
from gsmn.task.instructions import Instruction
from gsmn.world.spec import WorldSpec

_ARRAYS = ("images", "T_world_camera", "K", "poses", "actions")
_TMP_SUFFIX = ".tmp.npz"


class StoreError(ValueError):
    """A store or one of its episodes is missing or malformed."""


class EpisodeStore:
    """A folder of episodes keyed by name (e.g. "env_000070")."""

    def __init__(self, root: Path | str):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self._sweep()

    def path(self, key: str) -> Path:
        return self.root / f"{key}.npz"

    def keys(self) -> list[str]:
        """The whole episodes' keys; a write's temporary file (a dot name) is never one."""
        return sorted(p.stem for p in self.root.glob("*.npz") if not p.name.startswith("."))

    def __len__(self) -> int:
        return len(self.keys())

    def __contains__(self, key: str) -> bool:
        return self.path(key).is_file()

    def write(self, key: str, sample: EpisodeSample, meta: dict | None = None) -> None:
        """Write one episode atomically (a temporary file renamed into place)."""
        T = len(sample.images)
        for name, shape in (("T_world_camera", (T, 4, 4)), ("poses", (T, 3)), ("actions", (T, 3))):
            if getattr(sample, name).shape != shape:
                raise ValueError(f"episode {key}: {name} has shape {getattr(sample, name).shape}, expected {shape}")
        text = json.dumps({"world": sample.world.to_dict(), "instruction": _instruction_dict(sample.instruction),
                           "meta": meta or {}})
        tmp = self.root / f".{key}.{os.getpid()}{_TMP_SUFFIX}"
        try:
            np.savez_compressed(tmp, images=np.ascontiguousarray(sample.images, dtype=np.uint8),
                                T_world_camera=sample.T_world_camera.astype(np.float32),
                                K=sample.K.astype(np.float32), poses=sample.poses.astype(np.float32),
                                actions=sample.actions.astype(np.float32),
                                json=np.frombuffer(text.encode(), dtype=np.uint8))
            tmp.replace(self.path(key))
        except BaseException:  # a cancelled write (Ctrl-C, SIGTERM) leaves no part-written file
            tmp.unlink(missing_ok=True)
            raise

    def _sweep(self) -> None:
        """Remove temporary files left by writers that were killed outright (SIGKILL): their pid is gone."""
        for tmp in self.root.glob(f".*{_TMP_SUFFIX}"):
            pid = tmp.name[: -len(_TMP_SUFFIX)].rpartition(".")[2]
            if pid.isdigit() and not _alive(int(pid)):
                tmp.unlink(missing_ok=True)

    def read(self, key: str) -> EpisodeSample:
        return self.read_with_meta(key)[0]

    def read_with_meta(self, key: str) -> tuple[EpisodeSample, dict]:
        entries = self._load(key, (*_ARRAYS, "json"))
        d = json.loads(entries.pop("json").tobytes().decode())
        world = WorldSpec.from_dict(d["world"])
        sample = EpisodeSample(world=world, instruction=Instruction(**d["instruction"]), **entries)
        return sample, d["meta"]

    def read_meta(self, key: str) -> dict:
        """An episode's metadata alone, without decompressing its images."""
        return json.loads(self._load(key, ("json",))["json"].tobytes().decode())["meta"]

    def read_labels(self, key: str) -> np.ndarray:
        """An episode's expert labels (T, 3: v, omega, stop) alone, without decompressing its images."""
        return self._load(key, ("actions",))["actions"]

    def _load(self, key: str, names: tuple[str, ...]) -> dict[str, np.ndarray]:
        """The named arrays of an episode file (an .npz decompresses only the entries asked for)."""
        path = self.path(key)
        try:
            with np.load(path, allow_pickle=False) as f:
                return {name: f[name] for name in names}
        except FileNotFoundError:
            raise StoreError(f"no episode {key!r} in {self.root}") from None
        except (OSError, EOFError, KeyError, ValueError, zipfile.BadZipFile) as e:
            raise StoreError(f"episode file {path} is malformed: {e}") from e

    def delete(self, key: str) -> None:
        self.path(key).unlink(missing_ok=True)

    def __iter__(self) -> Iterator[EpisodeSample]:
        for key in self.keys():
            yield self.read(key)

    def frames(self) -> int:
        """Total number of frames (reads only the small pose arrays)."""
        return sum(len(self._load(key, ("poses",))["poses"]) for key in self.keys())


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def _instruction_dict(instruction: Instruction) -> dict:
    return {"text": instruction.text, "landmark_index": instruction.landmark_index,
            "noun_phrase": instruction.noun_phrase, "side": instruction.side, "goal_x": float(instruction.goal_x),
            "goal_y": float(instruction.goal_y), "ambiguous": bool(instruction.ambiguous)}
