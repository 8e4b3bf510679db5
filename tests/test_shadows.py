"""Baked shadows (gsmn/world/shadows.py): the paper's look in one render pass, against MuJoCo's own shadow passes."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from gsmn.config import CameraConfig, ConfigError, RunConfig
from gsmn.model.checkpoint import read_checkpoint_config
from gsmn.world import shadows
from gsmn.world.assets import load_catalogue
from gsmn.world.sim import HEADLIGHT, SUN, SUN_DIR, Simulator
from gsmn.world.spec import split_env_ids, world_for_env

pytestmark = pytest.mark.unit

PAPER = RunConfig()
ROOT = Path(__file__).resolve().parents[1]


def _sim(env_id: int, method: str) -> Simulator:
    config = dataclasses.replace(PAPER, camera=dataclasses.replace(PAPER.camera, shadow_method=method))
    return Simulator(world_for_env(env_id, config.world), config, load_catalogue())


def _flown_pairs(env_id: int, steps: int, *methods: str):
    """The forward camera's frames of one flight, rendered by each method (the physics is deterministic)."""
    sims = [_sim(env_id, m) for m in methods]
    try:
        for k in range(steps):
            for sim in sims:
                sim.step(1.6, 0.6 if (k // 6) % 2 else -0.6)
            yield [sim.render().astype(np.int16) for sim in sims]
    finally:
        for sim in sims:
            sim.close()


def test_baked_shadows_look_like_mujocos_shadow_passes():
    """Over flights in two test worlds, frames with baked shadows stay within a few levels of MuJoCo's shadow
    passes, where one pass without the light scaling caps the field's brightness (the clamp before the texture)."""
    near, capped = [], []
    for env_id in split_env_ids("test", 2):
        for mujoco_frame, baked in _flown_pairs(env_id, 12, "mujoco", "baked"):
            d = np.abs(baked - mujoco_frame)
            near.append((float((d.max(-1) > 16).mean()), float(d.mean())))
        no_scale = dataclasses.replace(PAPER, camera=dataclasses.replace(PAPER.camera, shadows=False))
        sim, reference = Simulator(world_for_env(env_id, no_scale.world), no_scale, load_catalogue()), _sim(env_id,
                                                                                                            "mujoco")
        try:
            capped.append(float((np.abs(sim.render().astype(int) - reference.render().astype(int)).max(-1)
                                 > 16).mean()))
        finally:
            sim.close()
            reference.close()
    over, mean_abs = np.mean(near, axis=0)
    assert over < 0.025 and mean_abs < 2.0, (over, mean_abs)
    assert min(capped) > 0.1, capped


def test_baked_shadows_fall_where_mujocos_fall_seen_from_above():
    """In the top-down view the texels that MuJoCo's shadow map darkens (against the same view with nothing baked)
    are the ones the baked shadows darken."""
    env_id = split_env_ids("test", 2)[1]

    def topdown(method: str) -> np.ndarray:
        sim = _sim(env_id, method)
        try:
            return sim.render_topdown(512).astype(float)
        finally:
            sim.close()

    real_cover = shadows.shadow_cover
    shadows.shadow_cover = lambda *a, **k: np.zeros_like(real_cover(*a, **k))
    try:
        lit = topdown("baked")
    finally:
        shadows.shadow_cover = real_cover
    colours, counts = np.unique(lit.reshape(-1, 3), axis=0, return_counts=True)
    checker = colours[np.argsort(counts)[-2:]]  # the lit field's two colours, the commonest in the view
    field = (np.abs(lit[:, :, None, :] - checker).max(-1) <= 8).any(-1)
    theirs, ours = (field & ((lit - topdown(m))[..., 1] > 25) for m in ("mujoco", "baked"))
    iou = (theirs & ours).sum() / (theirs | ours).sum()
    assert theirs.sum() > 2000 and iou > 0.85, (theirs.sum(), iou)


def test_the_field_texture_is_the_checker_where_nothing_shadows_it():
    sim = _sim(split_env_ids("test", 1)[0], "baked")
    try:
        grass, gh, gw = shadows._texture(sim.model, shadows.GRASS_TEXTURE)
        field, fh, fw = shadows._texture(sim.model, shadows.FIELD_TEXTURE)
        assert (fh, fw) == (gh * shadows.GRASS_REPEAT, gw * shadows.GRASS_REPEAT)
        values = {tuple(v) for v in grass.reshape(-1, grass.shape[-1])}
        lit = np.array([tuple(v) in values for v in field.reshape(-1, field.shape[-1])])
        assert 0.8 < lit.mean() < 1.0  # most of the field is lit checker, the rest darkened by shadows
    finally:
        sim.close()


def test_the_shadow_method_is_checked_and_a_config_saved_without_it_ran_mujocos():
    with pytest.raises(ConfigError, match="shadow_method"):
        CameraConfig(shadow_method="raytraced")
    assert CameraConfig().shadow_method == "baked"
    saved = RunConfig().to_dict()
    assert RunConfig.from_dict(saved).camera.shadow_method == "baked"  # written now: read as written
    del saved["camera"]["shadow_method"]  # a checkpoint, evaluation or job folder saved before the field existed
    assert RunConfig.from_dict(saved).camera.shadow_method == "mujoco"
    assert RunConfig.from_dict(saved) == dataclasses.replace(RunConfig(), camera=CameraConfig(shadow_method="mujoco"))
    shipped = read_checkpoint_config(ROOT / "checkpoints" / "gsmn")
    assert shipped.camera.shadow_method == "mujoco"  # the shipped GSMN was trained so


def test_landmark_faces_in_shadow_are_split_off_darker_and_the_surface_is_kept():
    """Each landmark part comes back as the same surface (split faces cover their originals' area exactly), its
    faces in another's shadow darker by a factor of SHADE_BINS and facing the sun, the others untouched; MuJoCo's
    own ray casting confirms a shaded face's centre is shadowed."""
    config = dataclasses.replace(PAPER, camera=dataclasses.replace(PAPER.camera, shadow_method="baked"))
    world, catalogue = world_for_env(split_env_ids("test", 2)[1], config.world), load_catalogue()
    sim = _sim(world.env_id, "mujoco")  # the unsplit world, for its rays
    try:
        blocked = shadows.ray_test(sim.model, sim.data, sim.model.body("drone").id)
        shades = shadows.face_shades(world, catalogue, np.array(SUN_DIR), HEADLIGHT, SUN, blocked)
        toward = -np.array(SUN_DIR) / np.linalg.norm(SUN_DIR)
        shaded = 0
        for (i, k, _, placed, faces), key in zip(shadows._world_parts(world, catalogue), sorted(shades), strict=True):
            assert key == (i, k)
            local, out_faces, shade = shades[key]
            lm = world.landmarks[i]
            c, s = np.cos(lm.yaw), np.sin(lm.yaw)
            out_world = (local * lm.scale) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [lm.x, lm.y, 0]

            def area(v, f):
                t = v[f]
                return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)

            assert area(out_world, out_faces).sum() == pytest.approx(area(placed, faces).sum(), rel=1e-9)
            assert set(np.unique(shade)) <= {1.0, *shadows.SHADE_BINS}
            dark = shade < 1
            if dark.any():
                t = out_world[out_faces[dark]]
                normal = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
                assert (normal @ toward > 0).all()
                assert blocked(t.mean(axis=1) + 2e-3 * toward, toward).all()
                shaded += int(dark.sum())
        assert shaded > 50  # this world's landmarks shadow parts of themselves
    finally:
        sim.close()
