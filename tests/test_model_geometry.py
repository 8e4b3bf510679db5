"""Model geometry against the real simulator: ground projection, coverage, leaky integrator, frame changes.

No trained network: the image's own colour channels are pushed through the projection, so a landmark's colour
must land on its true world cell. Pixel convention (docs/design.md): the top-left pixel's centre is (0.5, 0.5).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from gsmn.config import preset
from gsmn.geometry import project_points
from gsmn.model.frames import robot_to_world, robot_to_world_theta, world_to_robot, world_to_robot_theta
from gsmn.model.grid import MapGeometry, invert_rigid_2d, world_from_robot
from gsmn.model.projection import project_to_ground
from gsmn.model.semantic_map import accumulate, leaky_integrate
from gsmn.world.env import Action, Env

pytestmark = pytest.mark.unit

TINY = preset("tiny")
GEOMETRY = MapGeometry(TINY.world.field_size, TINY.model.map_size, TINY.model.robot_map_size)
SIZE = (TINY.camera.width, TINY.camera.height)
ENV_IDS = (70, 71, 72)


@pytest.fixture(scope="module")
def observations():
    """First observation of a few test environments, and one after turning around."""
    out = {}
    with Env(TINY) as env:
        for env_id in ENV_IDS:
            obs = env.reset(env_id)
            out[env_id] = (env.world, obs)
        env.reset(ENV_IDS[0])
        for _ in range(3):  # about 110 deg to the right: part of the field in view, part behind
            turned = env.step(Action(0.0, -2.44))
        out["turned"] = (env.world, turned)
    return out


def colour_map(obs, features: torch.Tensor | None = None):
    """Project the image colours (or given features (C, h, w)) onto the ground for one observation."""
    if features is None:
        features = torch.from_numpy(obs.image).permute(2, 0, 1).float() / 255  # (3, H, W)
    T = torch.from_numpy(obs.T_world_camera).float()[None]
    K = torch.from_numpy(obs.K).float()[None]
    projected, coverage = project_to_ground(features[None], T, K, GEOMETRY, SIZE)
    return projected[0], coverage[0, 0]


def cell_projections(obs) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (n, n, 2) and depths (n, n) of every world cell centre, by the numpy reference."""
    centres = GEOMETRY.world_cell_centres().numpy().reshape(-1, 2)
    points = np.concatenate([centres, np.zeros((len(centres), 1))], axis=1)
    uv, depth = project_points(obs.K, obs.T_world_camera, points)
    n = GEOMETRY.map_size
    return uv.reshape(n, n, 2), depth.reshape(n, n)


def bilinear(image: np.ndarray, u: float, v: float) -> np.ndarray:
    """Bilinear sample of an (H, W, C) image at continuous pixel coordinates (pixel centres at +0.5)."""
    x, y = u - 0.5, v - 0.5
    x0, y0 = int(math.floor(x)), int(math.floor(y))
    fx, fy = x - x0, y - y0
    H, W = image.shape[:2]

    def at(r, c):
        return image[min(max(r, 0), H - 1), min(max(c, 0), W - 1)].astype(float)

    return ((1 - fy) * ((1 - fx) * at(y0, x0) + fx * at(y0, x0 + 1))
            + fy * ((1 - fx) * at(y0 + 1, x0) + fx * at(y0 + 1, x0 + 1)))


def test_world_cell_layout_is_north_up():
    centres = GEOMETRY.world_cell_centres()
    s = GEOMETRY.cell_size
    assert centres[0, 0].tolist() == pytest.approx([s / 2, 30 - s / 2])  # top-left: north-west corner
    assert centres[-1, -1].tolist() == pytest.approx([30 - s / 2, s / 2])  # bottom-right: south-east
    assert GEOMETRY.world_cell_of(torch.tensor([[0.1, 29.9], [29.9, 0.1], [14.0, 16.0]])).tolist() == \
        [[0, 0], [31, 31], [14, 14]]


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_projection_samples_the_pixel_each_ground_cell_projects_to(observations, env_id):
    """Every world cell reads the image colour at the pixel the numpy camera model puts its centre on."""
    _, obs = observations[env_id]
    projected, coverage = colour_map(obs)
    uv, depth = cell_projections(obs)
    W, H = SIZE
    checked = 0
    for r in range(GEOMETRY.map_size):
        for c in range(GEOMETRY.map_size):
            u, v = uv[r, c]
            if depth[r, c] > 0 and 1 <= u <= W - 1 and 1 <= v <= H - 1:
                expected = bilinear(obs.image, u, v) / 255
                np.testing.assert_allclose(projected[:, r, c].numpy(), expected, atol=2e-3)
                checked += 1
    assert checked > 200  # from a start corner the camera sees most of the field


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_feature_cells_cover_eight_by_eight_pixel_blocks(observations, env_id):
    """With an 18x32 feature map whose value is its column (row) index, a cell projecting to pixel (u, v) reads
    u / 8 - 0.5 (v / 8 - 0.5): feature cell (i, j) covers pixels [8j, 8j + 8) x [8i, 8i + 8)."""
    _, obs = observations[env_id]
    h, w = SIZE[1] // 8, SIZE[0] // 8
    rows, cols = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                                indexing="ij")
    projected, _ = colour_map(obs, torch.stack([cols, rows]))
    uv, depth = cell_projections(obs)
    inside = (depth > 0) & (uv[..., 0] > 8) & (uv[..., 0] < SIZE[0] - 8) & (uv[..., 1] > 8) & (uv[..., 1] < SIZE[1] - 8)
    assert inside.sum() > 200
    np.testing.assert_allclose(projected[0].numpy()[inside], uv[..., 0][inside] / 8 - 0.5, atol=1e-3)
    np.testing.assert_allclose(projected[1].numpy()[inside], uv[..., 1][inside] / 8 - 0.5, atol=1e-3)


def test_visible_landmarks_light_up_their_world_cells():
    """Paint each landmark in its own colour channel (from the simulator's segmentation image) and project: every
    landmark whose base is in view lights up, in its own channel, the map cells at its true world position."""
    checked = exact = 0
    with Env(TINY) as env:
        for env_id in range(70, 76):
            obs = env.reset(env_id)
            world, sim = env.world, env.sim
            segmentation = sim.render_segmentation()  # (H, W) geom ids
            landmark_of_pixel = np.full(segmentation.shape, -1)
            for g in np.unique(segmentation):
                m = sim.landmark_of_geom(int(g))
                landmark_of_pixel[segmentation == g] = -1 if m is None else m
            painted = torch.from_numpy(np.stack([landmark_of_pixel == m for m in range(len(world.landmarks))])
                                       .astype(np.float32))  # (M, H, W)
            projected, _ = colour_map(obs, painted)
            for m, lm in enumerate(world.landmarks):
                uv, depth = project_points(obs.K, obs.T_world_camera, np.array([[lm.x, lm.y, 0.0]]))
                u, v = np.floor(uv[0]).astype(int)
                if not (depth[0] > 0 and 0 <= u < SIZE[0] and 0 <= v < SIZE[1]) or landmark_of_pixel[v, u] != m:
                    continue  # out of view, or its base hidden (behind another landmark, or a thin pole)
                r, c = GEOMETRY.world_cell_of(torch.tensor([lm.x, lm.y])).tolist()
                around = projected[m, max(r - 1, 0):r + 2, max(c - 1, 0):c + 2]
                assert around.max() > 0.5, f"env {env_id}: {lm.model} does not light up around its cell {(r, c)}"
                checked += 1
                exact += bool(projected[m, r, c] > 0.5)
    assert checked >= 25
    assert exact >= 0.7 * checked  # thin bases (trunks, poles) may miss the very cell of their centre


@pytest.mark.parametrize("key", [*ENV_IDS, "turned"])
def test_coverage_is_one_in_view_and_zero_behind(observations, key):
    _, obs = observations[key]
    _, coverage = colour_map(obs)
    uv, depth = cell_projections(obs)
    W, H = SIZE
    well_inside = (depth > 0) & (uv[..., 0] > 4) & (uv[..., 0] < W - 4) & (uv[..., 1] > 4) & (uv[..., 1] < H - 4)
    outside = (depth <= 0) | (uv[..., 0] < -4) | (uv[..., 0] > W + 4) | (uv[..., 1] < -4) | (uv[..., 1] > H + 4)
    assert well_inside.sum() > 50 and outside.sum() > 0
    if key == "turned":
        assert (depth <= 0).sum() > 100
    assert coverage.numpy()[well_inside].min() > 0.999
    assert coverage.numpy()[outside].max() == 0.0
    assert coverage.min() >= 0 and coverage.max() <= 1 + 1e-6


def test_leaky_integrator_keeps_unobserved_cells(observations):
    _, first = observations[ENV_IDS[0]]
    _, turned = observations["turned"]
    F1, M1 = colour_map(first)
    F2, M2 = colour_map(turned)
    S1 = leaky_integrate(None, F1[None], M1[None, None], 0.2)
    assert torch.equal(S1[0], F1)  # first step: S = F
    S2 = leaky_integrate(S1, F2[None], M2[None, None], 0.2)[0]
    unseen = M2 == 0
    assert unseen.sum() > 100 and (M2 > 0.999).sum() > 50
    assert torch.equal(S2[:, unseen], F1[:, unseen])  # unobserved: unchanged, bit for bit
    seen = M2 > 0.999
    torch.testing.assert_close(S2[:, seen], (0.8 * F1 + 0.2 * F2)[:, seen], atol=1e-4, rtol=0)
    # The sequence form agrees with the step form.
    seq = accumulate(torch.stack([F1, F2])[None], torch.stack([M1, M2])[None, :, None], 0.2)
    torch.testing.assert_close(seq[0, 1], S2)


def hot_cell_map(xy: tuple[float, float]) -> torch.Tensor:
    """A world map (1, 1, n, n) that is 1 at the cell containing xy."""
    m = torch.zeros(1, 1, GEOMETRY.map_size, GEOMETRY.map_size)
    r, c = GEOMETRY.world_cell_of(torch.tensor(xy)).tolist()
    m[0, 0, r, c] = 1.0
    return m, GEOMETRY.world_cell_centres()[r, c]


def peak(map_r: torch.Tensor) -> tuple[float, float]:
    """Weighted centroid (row, col) of a single-channel map (1, 1, h, w)."""
    m = map_r[0, 0].clamp(min=0)
    rows, cols = torch.meshgrid(torch.arange(m.shape[0], dtype=torch.float32),
                                torch.arange(m.shape[1], dtype=torch.float32), indexing="ij")
    return float((m * rows).sum() / m.sum()), float((m * cols).sum() / m.sum())


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_world_to_robot_puts_ahead_up_and_left_left(observations, env_id):
    """From the simulator's start heading, 10 m into the field: a cell 8 m ahead lands straight up the robot map,
    one 8 m to the left on its left, one 8 m to the right on its right."""
    _, obs = observations[env_id]
    yaw = float(obs.pose.yaw)
    x, y = float(obs.pose.position[0]) + 10 * math.cos(yaw), float(obs.pose.position[1]) + 10 * math.sin(yaw)
    pose = torch.tensor([[x, y, yaw]])
    centre = GEOMETRY.robot_map_size / 2 - 0.5  # row/col index of the drone's position (between cells)
    s = GEOMETRY.cell_size
    for name, angle in (("ahead", 0.0), ("left", math.pi / 2), ("right", -math.pi / 2)):
        hot, cell_xy = hot_cell_map((x + 8 * math.cos(yaw + angle), y + 8 * math.sin(yaw + angle)))
        # Where the hot cell's centre really is, in robot coordinates (forward, left).
        d = cell_xy.numpy() - np.array([x, y])
        fwd = d[0] * math.cos(yaw) + d[1] * math.sin(yaw)
        left = -d[0] * math.sin(yaw) + d[1] * math.cos(yaw)
        row, col = peak(world_to_robot(hot, pose, GEOMETRY))
        # Bilinear resampling of one hot cell at an angle: its centroid lands within a quarter cell.
        assert row == pytest.approx(centre - fwd / s, abs=0.25), name
        assert col == pytest.approx(centre - left / s, abs=0.25), name
        ahead, leftward = centre - row, centre - col  # cells
        if name == "ahead":
            assert abs(leftward) < 1.0 and ahead > 7
        elif name == "left":
            assert abs(ahead) < 1.0 and leftward > 7
        else:
            assert abs(ahead) < 1.0 and leftward < -7


def test_world_to_robot_heading_north_is_a_shift():
    """A drone at a cell corner heading north (yaw 90 deg) sees the world map shifted, unresampled."""
    s = GEOMETRY.cell_size
    m = torch.rand(1, 2, GEOMETRY.map_size, GEOMETRY.map_size)
    pose = torch.tensor([[10 * s, 20 * s, math.pi / 2]])  # column 10 boundary, row 12 boundary (north-up)
    r = world_to_robot(m, pose, GEOMETRY)
    half = GEOMETRY.robot_map_size // 2
    # world row 12 - half + i, col 10 - half + j  ->  robot (i, j)
    torch.testing.assert_close(r[0, :, half - 12:half - 12 + 32, half - 10:half - 10 + 32], m[0], atol=1e-5, rtol=0)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_robot_to_world_inverts_world_to_robot(observations, env_id):
    _, obs = observations[env_id]
    pose = torch.tensor([[obs.pose.position[0], obs.pose.position[1], obs.pose.yaw]], dtype=torch.float32)
    xy = GEOMETRY.world_cell_centres()
    smooth = torch.stack([torch.sin(xy[..., 0] / 5) * torch.cos(xy[..., 1] / 7), xy[..., 0] / 30])[None]
    back = robot_to_world(world_to_robot(smooth, pose, GEOMETRY), pose, GEOMETRY)
    # Compare away from the field's edge (edge cells mix in the zero padding) and where the robot map reaches:
    # it is 60 m across, so from a corner facing the diagonal the farthest corner of the field (42 m) is cut off.
    d = xy - pose[0, :2]
    c, s = math.cos(float(pose[0, 2])), math.sin(float(pose[0, 2]))
    fwd, left = d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c
    reach = GEOMETRY.robot_half_extent - 1.5 * GEOMETRY.cell_size
    keep = (fwd.abs() < reach) & (left.abs() < reach)
    keep[[0, -1], :] = False
    keep[:, [0, -1]] = False
    assert keep.sum() > 500
    torch.testing.assert_close(back[0][:, keep], smooth[0][:, keep], atol=0.03, rtol=0)
    # A hot cell comes back to the same place.
    hot, _ = hot_cell_map((12.0, 17.0))
    assert peak(robot_to_world(world_to_robot(hot, pose, GEOMETRY), pose, GEOMETRY)) == \
        pytest.approx(peak(hot), abs=0.25)


def test_frame_change_is_batched_per_sample():
    m = torch.rand(3, 2, GEOMETRY.map_size, GEOMETRY.map_size)
    poses = torch.tensor([[5.0, 5.0, 0.3], [20.0, 10.0, 2.0], [15.0, 25.0, -1.0]])
    together = world_to_robot(m, poses, GEOMETRY)
    for i in range(3):
        torch.testing.assert_close(together[i:i + 1], world_to_robot(m[i:i + 1], poses[i:i + 1], GEOMETRY))
    assert F.mse_loss(together[0], together[1]) > 0


def test_closed_form_frame_matrices_equal_the_composed_transforms():
    """frames.py writes the affine_grid matrices out; they are the products of grid.py's named transforms."""
    poses = torch.tensor([[5.0, 5.0, 0.3], [20.0, 10.0, 2.0], [15.0, 25.0, -1.0], [0.0, 30.0, math.pi]])
    g = GEOMETRY
    composed = g.normalised_from_world(poses) @ world_from_robot(poses) @ g.robot_from_normalised(poses)
    torch.testing.assert_close(world_to_robot_theta(poses, g), composed[:, :2])
    inverse = g.normalised_from_robot(poses) @ invert_rigid_2d(world_from_robot(poses)) @ g.world_from_normalised(poses)
    torch.testing.assert_close(robot_to_world_theta(poses, g), inverse[:, :2])
