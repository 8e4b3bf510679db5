"""On-disk landmark assets: binary STL meshes plus a catalogue JSON, written from `gsmn.world.landmarks`.

Layout under the assets directory (default ``<repo>/assets``, overridable with the ``GSMN_ASSETS``
environment variable)::

    landmarks/catalogue.json              {"version": 1, "models": [...]} in CATALOGUE (class id) order
    landmarks/<name>/part_<k>.stl         one flat-coloured part of a model, binary STL

Each catalogue entry holds the model's name, noun phrase, radius class, height, footprint radius,
``axis_z`` (a height in the middle of the longest stretch of the vertical axis inside the model) and its
parts (file, rgba, sha256).  Writing is deterministic: the same code gives the same bytes.

The simulator and the dashboard both read the meshes through `load_catalogue`, so they show identical
models.  Build the files with ``python scripts/build_assets.py``.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from trimesh.exchange.stl import export_stl

from gsmn.world.landmarks import CATALOGUE, axis_z, footprint_radius, merged_arrays

ASSETS_DIR: Path = Path(os.environ.get("GSMN_ASSETS") or Path(__file__).resolve().parents[2] / "assets")
CATALOGUE_VERSION = 1
_STL_RECORD = np.dtype([("normal", "<f4", (3,)), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])


@dataclass(frozen=True, eq=False)
class AssetPart:
    """One flat-coloured mesh part: vertices (V, 3) float32, faces (F, 3) int32 (both read-only)."""

    vertices: np.ndarray
    faces: np.ndarray
    rgba: tuple[float, float, float, float]


@dataclass(frozen=True)
class AssetModel:
    """A landmark model as loaded from disk."""

    name: str
    noun_phrase: str
    radius: float
    height: float
    footprint_radius: float
    axis_z: float
    parts: tuple[AssetPart, ...]


def _r6(x: float) -> float:
    return round(float(x), 6) + 0.0


def write_assets(out_dir: Path = ASSETS_DIR) -> None:
    """Build every catalogue model and write ``out_dir/landmarks`` from scratch (stale files removed)."""
    root = Path(out_dir) / "landmarks"
    if root.exists():
        shutil.rmtree(root)
    root.mkdir(parents=True)
    models = []
    for model in CATALOGUE:
        parts = model.build()
        vertices, faces = merged_arrays(parts)
        (root / model.name).mkdir()
        entries = []
        for k, part in enumerate(parts):
            data = export_stl(part.mesh)
            rel = f"landmarks/{model.name}/part_{k}.stl"
            (Path(out_dir) / rel).write_bytes(data)
            entries.append({"file": rel, "rgba": [_r6(c) for c in part.rgba],
                            "sha256": hashlib.sha256(data).hexdigest()})
        models.append({"name": model.name, "noun_phrase": model.noun_phrase, "radius": _r6(model.radius),
                       "height": _r6(vertices[:, 2].max()), "footprint_radius": _r6(footprint_radius(vertices)),
                       "axis_z": _r6(axis_z(parts)), "parts": entries})
    text = json.dumps({"version": CATALOGUE_VERSION, "models": models}, sort_keys=True, indent=1)
    (root / "catalogue.json").write_text(text + "\n", encoding="utf-8")
    _load.cache_clear()


def read_stl(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Binary STL file -> (vertices float32 (V, 3), faces int32 (F, 3)); see `parse_stl`."""
    return parse_stl(Path(path).read_bytes(), str(path))


def parse_stl(data: bytes, name: str = "<stl>") -> tuple[np.ndarray, np.ndarray]:
    """Binary STL bytes -> (vertices float32 (V, 3), faces int32 (F, 3)) with coincident corners merged.

    Vertices come out in sorted order (np.unique), so the result depends only on the bytes."""
    count = int(np.frombuffer(data, "<u4", 1, 80)[0]) if len(data) >= 84 else -1
    if count < 0 or len(data) != 84 + count * _STL_RECORD.itemsize:
        raise ValueError(f"{name}: not a binary STL")
    corners = np.frombuffer(data, _STL_RECORD, count, 84)["vertices"].reshape(-1, 3)
    vertices, inverse = np.unique(corners, axis=0, return_inverse=True)
    faces = inverse.reshape(-1, 3).astype(np.int32)
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    return np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces)


def load_catalogue(assets_dir: Path = ASSETS_DIR) -> tuple[AssetModel, ...]:
    """All landmark models from ``assets_dir/landmarks`` in catalogue order (cached per resolved path)."""
    return _load(Path(assets_dir).resolve())


@functools.lru_cache(maxsize=8)
def _load(assets_dir: Path) -> tuple[AssetModel, ...]:
    index = assets_dir / "landmarks" / "catalogue.json"
    if not index.is_file():
        raise FileNotFoundError(f"landmark catalogue {index} not found; build it with "
                                f"`python scripts/build_assets.py --out {assets_dir}`")
    catalogue = json.loads(index.read_text(encoding="utf-8"))
    if catalogue.get("version") != CATALOGUE_VERSION:
        raise ValueError(f"{index}: version {catalogue.get('version')!r}, expected {CATALOGUE_VERSION}; "
                         "rebuild with `python scripts/build_assets.py`")
    models = []
    for entry in catalogue["models"]:
        parts = []
        for part in entry["parts"]:
            path = assets_dir / part["file"]
            if not path.is_file():
                raise FileNotFoundError(f"landmark mesh {path} missing; rebuild with `python scripts/build_assets.py`")
            data = path.read_bytes()
            if hashlib.sha256(data).hexdigest() != part["sha256"]:
                raise ValueError(f"{path} does not match catalogue.json; rebuild with `python scripts/build_assets.py`")
            vertices, faces = parse_stl(data, str(path))
            vertices.setflags(write=False)
            faces.setflags(write=False)
            parts.append(AssetPart(vertices, faces, tuple(float(c) for c in part["rgba"])))
        models.append(AssetModel(entry["name"], entry["noun_phrase"], float(entry["radius"]), float(entry["height"]),
                                 float(entry["footprint_radius"]), float(entry["axis_z"]), tuple(parts)))
    return tuple(models)
