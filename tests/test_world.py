"""World sampling, simulator, camera and environment tests, all against the real MuJoCo model."""

from __future__ import annotations

import itertools
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from gsmn.config import ConfigError, DroneConfig, RunConfig, WorldConfig, preset, with_overrides
from gsmn.geometry import in_image, project_points
from gsmn.world.assets import load_catalogue
from gsmn.world.env import Action, Env
from gsmn.world.landmarks import CATALOGUE
from gsmn.world.sim import Simulator, build_spec
from gsmn.world.spec import WorldSpec, on_field, split_env_ids, split_of, world_for_env

pytestmark = pytest.mark.unit

TINY = preset("tiny")
IDS = range(300)


@pytest.fixture(scope="module")
def worlds() -> list[WorldSpec]:
    return [world_for_env(i) for i in IDS]


# -- sampling ---------------------------------------------------------------------------------------
def test_sampled_worlds_obey_placement_rules(worlds):
    c = WorldConfig()
    counts = []
    for w in worlds:
        n = len(w.landmarks)
        counts.append(n)
        assert c.min_landmarks <= n <= c.max_landmarks
        assert len({lm.model for lm in w.landmarks}) == n, "landmarks are drawn without replacement"
        start = w.start_position
        for lm in w.landmarks:
            assert c.edge_margin <= lm.x <= c.field_size - c.edge_margin
            assert c.edge_margin <= lm.y <= c.field_size - c.edge_margin
            assert np.linalg.norm(lm.position - start) >= lm.radius + c.start_clearance
            model = CATALOGUE[lm.class_id]
            assert model.name == lm.model and model.noun_phrase == lm.noun_phrase
            assert c.radius_scale_min <= lm.scale <= c.radius_scale_max
            assert lm.radius == pytest.approx(model.radius * lm.scale)
        for a, b in itertools.combinations(w.landmarks, 2):
            assert np.linalg.norm(a.position - b.position) >= a.radius + b.radius + c.landmark_gap
        for lake in w.lakes:
            for lm in w.landmarks:
                assert math.hypot(lake.x - lm.x, lake.y - lm.y) >= max(lake.radius_x, lake.radius_y) + lm.radius
    # The sampler should spread counts, not collapse to the minimum (see docs/design.md).
    assert np.mean(counts) > 7 and max(counts) >= 9


def test_start_is_a_corner_facing_45_degrees_in(worlds):
    corners = set()
    for w in worlds:
        corners.add(w.start_corner)
        assert (w.start_x, w.start_y) in {(0, 0), (30, 0), (30, 30), (0, 30)}
        to_centre = math.atan2(15 - w.start_y, 15 - w.start_x)
        assert math.isclose(w.start_yaw, to_centre, abs_tol=1e-9)
        assert abs(abs(math.remainder(w.start_yaw, math.pi / 2)) - math.pi / 4) < 1e-9
    assert corners == {0, 1, 2, 3}


def test_on_field_includes_the_edges_and_nothing_beyond(worlds):
    w = worlds[0]
    assert w.on_field(w.start_position)  # the start is a corner
    for xy in [(0, 0), (30, 30), (15, 0), (0, 15), (12.5, 27.25)]:
        assert w.on_field(xy) and on_field(*xy, 30.0)
    for xy in [(-0.01, 15), (15, -0.01), (30.01, 15), (15, 30.01), (-1, -1), (float("nan"), 15)]:
        assert not w.on_field(xy) and not on_field(*xy, 30.0)
    assert on_field(40, 40, 50.0) and not on_field(40, 40, 30.0)


def test_same_id_same_world_and_different_ids_differ():
    assert world_for_env(123) == world_for_env(123)
    assert world_for_env(123) != world_for_env(124)
    assert world_for_env(123, WorldConfig(seed=1)) != world_for_env(123)
    w = world_for_env(42)
    assert WorldSpec.from_dict(json.loads(w.to_json())) == w


def test_splits_follow_the_original():
    assert [split_of(i) for i in (0, 69, 70, 84, 85, 99, 100, 170, 4999)] == [
        "train", "train", "test", "test", "dev", "dev", "train", "test", "dev"]
    first = [split_of(i) for i in range(1000)]
    assert (first.count("train"), first.count("test"), first.count("dev")) == (700, 150, 150)
    assert split_env_ids("test", 3) == [70, 71, 72]
    assert split_env_ids("dev", 2, start=99) == [99, 185]
    with pytest.raises(ValueError):
        split_of(-1)


def test_every_sampled_world_compiles(worlds):
    catalogue = load_catalogue()
    for w in worlds:
        model = build_spec(w, TINY, catalogue).compile()
        assert model.nbody == 3 + len(w.landmarks)  # world, drone, gimbal, one body per landmark


def test_config_validation_fails_clearly():
    with pytest.raises(ConfigError, match="min_landmarks"):
        WorldConfig(min_landmarks=9, max_landmarks=6)
    with pytest.raises(ConfigError, match="substeps"):
        DroneConfig(control_hz=7.0, physics_dt=0.005)
    with pytest.raises(ConfigError, match="no field"):
        with_overrides(RunConfig(), {"camera.pich_deg": "3"})
    assert with_overrides(RunConfig(), {"camera.pitch-deg": "30", "camera.shadows": "false"}).camera.pitch_deg == 30


# -- dynamics ---------------------------------------------------------------------------------------
def _fly(sim: Simulator, v: float, w: float, steps: int) -> list[tuple[float, float, float, float]]:
    """Per step: forward speed, lateral speed, world yaw rate, altitude."""
    out = []
    for _ in range(steps):
        sim.step(v, w)
        yaw = sim.yaw
        vel = sim.velocity_world
        fwd = vel[0] * math.cos(yaw) + vel[1] * math.sin(yaw)
        lat = -vel[0] * math.sin(yaw) + vel[1] * math.cos(yaw)
        out.append((fwd, lat, sim.yaw_rate, sim.position[2]))
    return out


def test_drone_tracks_velocity_and_yaw_rate_steps_and_holds_altitude():
    """Tolerances: within 0.05 m/s and 0.05 rad/s of a step command after 2 s; altitude within 0.1 m."""
    sim = Simulator(world_for_env(0), TINY)
    alt = TINY.drone.altitude
    try:
        for v, w in [(1.6, 0.0), (0.5, 0.0), (1.0, 1.2), (1.6, -2.44), (0.0, 0.0), (0.8, 2.44)]:
            trace = _fly(sim, v, w, 15)  # 3 s at 5 Hz
            for fwd, lat, yaw_rate, _ in trace[10:]:  # settled after 2 s
                assert fwd == pytest.approx(v, abs=0.05)
                assert abs(lat) < 0.05
                assert yaw_rate == pytest.approx(w, abs=0.05)
            assert all(abs(z - alt) < 0.1 for *_, z in trace)
        # Commands beyond the limits are clipped: no reversing, 1.6 m/s, 2.44 rad/s.
        fwd, _, yaw_rate, _ = _fly(sim, 5.0, 10.0, 15)[-1]
        assert fwd == pytest.approx(1.6, abs=0.05) and yaw_rate == pytest.approx(2.44, abs=0.05)
        fwd, *_ = _fly(sim, -1.0, 0.0, 15)[-1]
        assert abs(fwd) < 0.05
    finally:
        sim.close()


def test_drone_moves_by_physics_not_teleport():
    """Position integrates velocity: after 1 s from hover at a 1.6 m/s command, it has not yet gone 1.6 m."""
    sim = Simulator(world_for_env(1), TINY)
    try:
        p0 = sim.position
        sim.step(1.6, 0.0)
        d1 = np.linalg.norm(sim.position - p0)
        for _ in range(4):
            sim.step(1.6, 0.0)
        d5 = np.linalg.norm(sim.position - p0)
        assert 0 < d1 < 0.32 * 0.9 and 0.6 < d5 < 1.6
        assert sim.data.ctrl[0] > 0  # thrust holds it up
    finally:
        sim.close()


# -- camera -----------------------------------------------------------------------------------------
def test_every_landmark_centre_is_in_view_from_the_start(worlds):
    sim = Simulator(worlds[0], TINY)
    K = sim.K
    cam = TINY.camera
    try:
        for w in worlds[:200]:
            if w != sim.world:
                sim.close()
                sim = Simulator(w, TINY)
            centres = np.array([[lm.x, lm.y, 0.0] for lm in w.landmarks])
            uv, depth = project_points(K, sim.T_world_camera, centres)
            assert in_image(uv, depth, cam.width, cam.height).all(), (w.env_id, uv)
    finally:
        sim.close()


def test_intrinsics_match_the_paper_camera():
    sim = Simulator(world_for_env(0), TINY)
    try:
        K = sim.K
        assert K[0, 0] == pytest.approx(128.0) and K[1, 1] == pytest.approx(128.0)
        assert (K[0, 2], K[1, 2]) == (128.0, 72.0)
        T = sim.T_world_camera
        R = T[:3, :3]
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) == pytest.approx(1.0)
        # z (optical axis) points along the heading, pitched down by the configured angle.
        pitch = math.degrees(math.asin(-R[2, 2]))
        assert pitch == pytest.approx(TINY.camera.pitch_deg, abs=0.5)
        heading = math.atan2(R[1, 2], R[0, 2])
        assert heading == pytest.approx(sim.world.start_yaw, abs=1e-3)
    finally:
        sim.close()


@pytest.mark.slow
def test_projected_landmark_centre_lands_on_that_landmark():
    """Project a point on each landmark's vertical axis with the exposed K and T_world_camera; the rendered
    pixel there must belong to that landmark (by segmentation) and show one of its colours, unless a nearer
    landmark occludes it."""
    catalogue = {m.name: m for m in load_catalogue()}
    hits = total = 0
    for env_id in range(24):
        w = world_for_env(env_id)
        sim = Simulator(w, TINY)
        try:
            sim.step(1.0, 0.3)  # a non-trivial pose, not only the start
            image, seg = sim.render(), sim.render_segmentation()
            T = sim.T_world_camera
            cam_pos = T[:3, 3]
            for i, lm in enumerate(w.landmarks):
                model = catalogue[lm.model]
                point = np.array([[lm.x, lm.y, model.axis_z * lm.scale]])
                uv, depth = project_points(sim.K, T, point)
                if not in_image(uv, depth, TINY.camera.width, TINY.camera.height)[0]:
                    continue
                u, v = int(uv[0, 0]), int(uv[0, 1])
                total += 1
                owner = sim.landmark_of_geom(int(seg[v, u]))
                if owner == i:
                    hits += 1
                    geom = int(seg[v, u])
                    part_rgb = np.array(sim.model.geom_rgba[geom][:3]) * 255
                    # Lit colour is the part colour times a positive light factor: the same hue.
                    pix = image[v, u].astype(float)
                    if np.linalg.norm(part_rgb) < 40:  # a near-black part renders dark
                        assert np.linalg.norm(pix) < 120, (env_id, lm.model, pix, part_rgb)
                    else:
                        cos = pix @ part_rgb / (np.linalg.norm(pix) * np.linalg.norm(part_rgb))
                        assert cos > 0.9, (env_id, lm.model, pix, part_rgb)
                else:
                    assert owner is not None, (env_id, lm.model, "projected point hits no landmark")
                    other = w.landmarks[owner]
                    assert np.linalg.norm(other.position - cam_pos[:2]) < np.linalg.norm(lm.position - cam_pos[:2])
        finally:
            sim.close()
    assert total > 100 and hits / total > 0.7  # every miss was checked to be an occlusion


# -- environment ------------------------------------------------------------------------------------
def test_same_id_gives_the_same_first_image_and_same_rollout():
    actions = [Action(1.6, 0.0)] * 5 + [Action(1.2, 0.8)] * 5 + [Action(0.4, -1.5)] * 3
    runs = []
    for _ in range(2):
        with Env(RunConfig()) as env:  # paper preset: shadows and anti-aliasing on
            obs = [env.reset(11, instruction="go to the left side of the rock")]
            obs += [env.step(a) for a in actions]
            runs.append(obs)
    a, b = runs
    for oa, ob in zip(a, b, strict=True):
        assert np.array_equal(oa.image, ob.image)
        assert np.array_equal(oa.pose.position, ob.pose.position)
        assert np.array_equal(oa.T_world_camera, ob.T_world_camera)
    assert a[-1].step == len(actions) and a[-1].time == pytest.approx(len(actions) / 5)
    assert not np.array_equal(a[0].image, a[-1].image)


def test_env_reset_reuses_and_replaces_worlds():
    with Env(TINY) as env:
        first = env.reset(5)
        env.step(Action(1.6, 0.5))
        again = env.reset(5)
        assert np.array_equal(first.image, again.image) and again.step == 0
        other = env.reset(6)
        assert env.world.env_id == 6 and not np.array_equal(first.image, other.image)
        assert env.instruction is None
    with pytest.raises(RuntimeError, match="reset"):
        Env(TINY).step(Action(1.0, 0.0))


# -- command line -----------------------------------------------------------------------------------
@pytest.mark.slow
def test_cli_world_json_and_pngs(tmp_path):
    out = subprocess.run([sys.executable, "-m", "gsmn.cli", "world", "--env-id", "17", "--json"],
                         capture_output=True, text=True, check=True).stdout
    d = json.loads(out)
    w = world_for_env(17)
    assert d["env_id"] == 17 and d["split"] == "train"
    assert [lm["name"] for lm in d["landmarks"]] == [lm.model for lm in w.landmarks]
    assert set(d["landmarks"][0]) >= {"name", "noun_phrase", "x", "y", "radius"}
    assert set(d["start"]) >= {"x", "y", "yaw"}
    subprocess.run([sys.executable, "-m", "gsmn.cli", "world", "--env-id", "17", "--out", str(tmp_path),
                    "--preset", "tiny"], check=True, capture_output=True)
    from PIL import Image

    assert Image.open(tmp_path / "env_17_camera.png").size == (256, 144)
    assert Image.open(tmp_path / "env_17_topdown.png").size[0] >= 512
    bad = subprocess.run([sys.executable, "-m", "gsmn.cli", "world", "--env-id", "-3"], capture_output=True,
                         text=True)
    assert bad.returncode == 2 and "non-negative" in bad.stderr


def _controller_as_vectors(ctl, qpos, qvel, v_cmd: float, omega_cmd: float) -> np.ndarray:
    """The cascaded controller in its vector form (what DroneController computed before it was written on floats
    for speed): the reference its float form must match. Its products go through numpy's dot and matmul, whose
    OpenBLAS kernels fuse multiply-adds on CPUs with FMA (AVX-512 ones among them): there the two forms differ in
    the last bits of rounding, and only there."""
    from gsmn.world.sim import GRAVITY, quat_to_R, yaw_of

    c = ctl.config
    R = quat_to_R(qpos[3:7])
    yaw = yaw_of(R)
    fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    left = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    v_world, omega_body = qvel[0:3], qvel[3:6]
    yaw_rate = float(R[2] @ omega_body)
    a_fwd = np.clip(c.velocity_gain * (v_cmd - v_world @ fwd), -ctl.max_tilt_acc, ctl.max_tilt_acc)
    a_left = np.clip(c.velocity_gain * (0.0 - v_world @ left) + yaw_rate * v_cmd, -ctl.max_tilt_acc,
                     ctl.max_tilt_acc)
    a_up = c.altitude_kp * (c.altitude - qpos[2]) - c.altitude_kd * v_world[2]
    thrust_world = c.mass * (a_fwd * fwd + a_left * left + np.array([0.0, 0.0, GRAVITY + a_up]))
    z_body = R[:, 2]
    thrust = max(0.0, float(thrust_world @ z_body))
    z_des = thrust_world / np.linalg.norm(thrust_world)
    err_body = R.T @ np.cross(z_body, z_des)
    rate_err = R.T @ np.array([0.0, 0.0, omega_cmd]) - omega_body
    torque = ctl.inertia * np.array([c.attitude_kp * err_body[0] + c.attitude_kd * rate_err[0],
                                     c.attitude_kp * err_body[1] + c.attitude_kd * rate_err[1],
                                     c.yaw_rate_gain * rate_err[2]])
    torque += np.cross(omega_body, ctl.inertia * omega_body)
    return np.array([thrust, torque[0], torque[1], torque[2]])


def _products_fuse() -> bool:
    """Whether numpy's 3-vector products round differently from the same sums written on floats on this CPU."""
    rng = np.random.default_rng(0)
    for _ in range(200):
        u, v = rng.normal(size=3), rng.normal(size=3)
        if float(u @ v) != float(u[0]) * float(v[0]) + float(u[1]) * float(v[1]) + float(u[2]) * float(v[2]):
            return True
    return False


def test_the_controller_on_floats_is_its_vector_form():
    """Every substep of flights with changing commands: the same thrust and torques, to the bit where numpy's
    products round as plain floats do, else to the last bits of rounding (_controller_as_vectors)."""
    import mujoco

    fused = _products_fuse()
    rng = np.random.default_rng(7)
    sim = Simulator(world_for_env(split_env_ids("test", 3)[2], TINY.world), TINY, load_catalogue())
    try:
        calls = 0
        for _ in range(40):
            v, w = rng.uniform(-0.5, 3.0), rng.uniform(-1.5, 1.5)
            for _ in range(TINY.drone.substeps):
                d = sim.data
                ours = sim.controller(d.qpos, d.qvel, v, w)
                vectors = _controller_as_vectors(sim.controller, d.qpos, d.qvel, v, w)
                if fused:
                    np.testing.assert_allclose(ours, vectors, rtol=1e-12, atol=1e-12, err_msg=str(calls))
                else:
                    assert np.array_equal(ours, vectors), calls
                d.ctrl[:] = ours
                mujoco.mj_step(sim.model, d)
                calls += 1
        assert abs(sim.yaw) > 0.1 and sim.position[2] > 0.5  # it flew: turned, and held its altitude
    finally:
        sim.close()
