"""Tests for the landmark catalogue (gsmn.world.landmarks) and its on-disk assets (gsmn.world.assets)."""

from __future__ import annotations

import re
from collections import Counter

import mujoco
import numpy as np
import pytest

from gsmn.world import catalogue
from gsmn.world import landmarks as lm
from gsmn.world.assets import ASSETS_DIR, load_catalogue, write_assets

pytestmark = pytest.mark.unit

SHARED = {"palm tree": 4, "rock": 4, "house": 3, "barrel": 3, "bush": 3, "well": 2, "mushroom": 2, "cone": 2,
          "box": 2, "christmas tree": 2, "tower": 2}


@pytest.fixture(scope="module")
def built() -> dict[str, list[lm.LandmarkPart]]:
    return {m.name: m.build() for m in lm.CATALOGUE}


def _winding_number(vertices: np.ndarray, faces: np.ndarray, point: np.ndarray) -> float:
    """Generalised winding number of a closed triangle mesh around a point (1 inside, 0 outside)."""
    tri = vertices[faces] - point
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    det = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la \
        + np.einsum("ij,ij->i", c, a) * lb
    return float(np.sum(2 * np.arctan2(det, den)) / (4 * np.pi))


def test_catalogue_names_and_size():
    names = [m.name for m in lm.CATALOGUE]
    assert len(names) == 63
    assert len(set(names)) == 63
    assert all(re.fullmatch(r"[a-z][a-z0-9]*(_[a-z0-9]+)*", n) for n in names)
    assert lm.model_by_name("fir_tree") is lm.CATALOGUE[names.index("fir_tree")]


def test_each_catalogue_entry_is_paired_with_its_builder_in_class_id_order():
    """gsmn.world.catalogue is the data (what world sampling and the model read); landmarks adds the meshes."""
    assert [(m.name, m.noun_phrase, m.radius) for m in lm.CATALOGUE] == \
        [(c.name, c.noun_phrase, c.radius) for c in catalogue.CATALOGUE]
    assert lm.NOUN_PHRASES == catalogue.NOUN_PHRASES
    with pytest.raises(KeyError):
        lm.model_by_name("no_such_landmark")


def test_noun_phrases_and_shared_multiplicities():
    counts = Counter(m.noun_phrase for m in lm.CATALOGUE)
    assert len(counts) == 45
    assert lm.NOUN_PHRASES == tuple(sorted(counts))
    assert all(re.fullmatch(r"[a-z]+( [a-z]+)*", p) for p in counts)
    assert {p: n for p, n in counts.items() if n > 1} == SHARED
    assert sum(1 for n in counts.values() if n == 1) == 34
    for phrase in ("fir tree", "wooden house", "red barrel", "lighthouse", "windmill", "gorilla", "traffic cone"):
        assert counts[phrase] == 1


def test_radius_classes_cover_range():
    radii = np.array([m.radius for m in lm.CATALOGUE])
    assert radii.min() >= 2.25 and radii.max() <= 3.75
    hist = np.histogram(radii, bins=6, range=(2.25, 3.75))[0]
    assert hist.min() >= 7, hist  # spread roughly evenly over the range


def test_geometry_conventions(built):
    for model in lm.CATALOGUE:
        parts = built[model.name]
        assert parts, model.name
        vertices, faces = lm.merged_arrays(parts)
        for part in parts:
            assert len(part.rgba) == 4 and part.rgba[3] == 1.0 and all(0.0 <= c <= 1.0 for c in part.rgba)
            assert len(part.mesh.faces) > 0
        assert abs(vertices[:, 2].min()) < 1e-6, model.name
        lo, hi = vertices[:, :2].min(axis=0), vertices[:, :2].max(axis=0)
        assert np.allclose((lo + hi) / 2, 0.0, atol=1e-4), model.name
        assert lm.footprint_radius(vertices) <= 0.8 * model.radius, model.name
        assert 0.8 <= vertices[:, 2].max() <= 8.0, model.name
        assert len(faces) <= 2500, (model.name, len(faces))


def test_vertical_axis_passes_through_solid(built):
    for model in lm.CATALOGUE:
        vertices, faces = lm.merged_arrays(built[model.name])
        hits = lm.axis_hits(vertices, faces)
        assert len(hits) >= 2, model.name
        z = lm.axis_z(built[model.name])
        assert _winding_number(vertices, faces, np.array([0.0, 0.0, z])) > 0.5, (model.name, z)


def test_build_is_deterministic(built):
    for name in ("rock_1", "bush_2", "stone_circle", "palm_tree_2", "globe"):
        again = lm.model_by_name(name).build()
        assert len(again) == len(built[name])
        for a, b in zip(again, built[name], strict=True):
            assert a.rgba == b.rgba
            assert np.array_equal(a.mesh.vertices, b.mesh.vertices)
            assert np.array_equal(a.mesh.faces, b.mesh.faces)


def test_assets_on_disk_match_generator(tmp_path):
    write_assets(tmp_path)
    fresh = {p.relative_to(tmp_path).as_posix(): p for p in (tmp_path / "landmarks").rglob("*") if p.is_file()}
    disk = {p.relative_to(ASSETS_DIR).as_posix(): p for p in (ASSETS_DIR / "landmarks").rglob("*") if p.is_file()}
    assert sorted(disk) == sorted(fresh), "assets/ is stale: run python scripts/build_assets.py"
    stale = [rel for rel in fresh if fresh[rel].read_bytes() != disk[rel].read_bytes()]
    assert not stale, f"assets/ is stale ({stale[:5]}): run python scripts/build_assets.py"


def test_load_catalogue(built):
    models = load_catalogue()
    assert load_catalogue() is models  # cached
    assert [m.name for m in models] == [m.name for m in lm.CATALOGUE]
    for asset, model in zip(models, lm.CATALOGUE, strict=True):
        assert asset.noun_phrase == model.noun_phrase and asset.radius == pytest.approx(model.radius)
        assert len(asset.parts) == len(built[model.name]) > 0
        for part, source in zip(asset.parts, built[model.name], strict=True):
            assert part.vertices.dtype == np.float32 and part.vertices.shape[1] == 3
            assert part.faces.dtype == np.int32 and part.faces.shape[1] == 3 and len(part.faces) > 0
            assert part.faces.min() >= 0 and part.faces.max() < len(part.vertices)
            assert part.rgba == pytest.approx(source.rgba, abs=1e-6)
        vertices = np.vstack([p.vertices for p in asset.parts]).astype(float)
        assert asset.height == pytest.approx(vertices[:, 2].max(), abs=1e-5)
        assert asset.footprint_radius == pytest.approx(lm.footprint_radius(vertices), abs=1e-5)
        assert 0.0 < asset.axis_z <= asset.height


def test_load_catalogue_missing(tmp_path):
    with pytest.raises(FileNotFoundError, match="build_assets"):
        load_catalogue(tmp_path / "nowhere")


def test_all_models_compile_in_mujoco():
    spec = mujoco.MjSpec()
    count = 0
    for i, model in enumerate(load_catalogue()):
        for k, part in enumerate(model.parts):
            mesh = spec.add_mesh(name=f"{model.name}_{k}")
            mesh.uservert = part.vertices.flatten()
            mesh.userface = part.faces.flatten()
            spec.worldbody.add_geom(name=f"geom_{i}_{k}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh.name,
                                    rgba=list(part.rgba), contype=0, conaffinity=0)
            count += 1
    compiled = spec.compile()
    assert compiled.nmesh == count == compiled.ngeom
