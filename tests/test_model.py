"""Contracts of the model package: data interface, shapes, purity, step-level pieces vs the sequence forward,
the policy, the losses and their ablation switches, gradients, checkpoints, and a tiny overfit check on real
expert episodes (all on CPU with the tiny preset)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from gsmn.cli import main
from gsmn.config import LossConfig, ModelConfig, RunConfig, preset
from gsmn.geometry import in_image, project_points
from gsmn.model import (
    KINDS,
    CheckpointError,
    EpisodeSample,
    GSMNOutputs,
    ModelPolicy,
    Vocabulary,
    build_model,
    collate,
    compute_losses,
    forward_batch,
    load_checkpoint,
    load_policy,
    read_checkpoint_kind,
    save_checkpoint,
)
from gsmn.model.checkpoint import average_checkpoints
from gsmn.model.fpv import memory_from_fpv
from gsmn.model.labels import make_labels
from gsmn.model.losses import TERMS
from gsmn.model.noise import perturb_poses
from gsmn.model.projection import invert_rigid
from gsmn.task.expert import Expert
from gsmn.task.instructions import SIDES, make_instruction
from gsmn.task.rollout import Task, task_for_env
from gsmn.world.env import Action, Env
from gsmn.world.landmarks import CATALOGUE

pytestmark = pytest.mark.unit

TINY = preset("tiny")
CHECKPOINTS = {p.name: p for p in (Path(__file__).resolve().parents[1] / "checkpoints").iterdir()
               if (p / "config.json").is_file()}
SIGMOID = dataclasses.replace(TINY, model=dataclasses.replace(TINY.model, filter_activation="sigmoid"))  # original
VOCABULARY = Vocabulary.default()


def record_expert(env: Env, env_id: int, config: RunConfig) -> tuple[EpisodeSample, list, Task]:
    """Fly the expert on an environment's task; return the episode, its observations and the task."""
    task = task_for_env(env_id, config)
    expert = Expert(task.path, config.expert, config.drone)
    obs = env.reset(env_id, task.instruction.text, task.world)
    observations, actions = [], []
    for _ in range(config.task.horizon):
        a = expert.act(obs.pose.position[:2], obs.pose.yaw)
        observations.append(obs)
        actions.append((a.v_norm, a.omega_norm, float(a.stop)))
        if a.stop:
            break
        obs = env.step(Action(a.forward_velocity, a.yaw_rate))
    sample = EpisodeSample(
        world=task.world, instruction=task.instruction,
        images=np.stack([o.image for o in observations]),
        T_world_camera=np.stack([o.T_world_camera for o in observations]).astype(np.float32),
        K=observations[0].K.astype(np.float32),
        poses=np.array([(o.pose.position[0], o.pose.position[1], o.pose.yaw) for o in observations], np.float32),
        actions=np.array(actions, np.float32))
    return sample, observations, task


def subsample(sample: EpisodeSample, steps: int) -> EpisodeSample:
    """`steps` evenly spaced steps of an episode, always including the first and the last (STOP)."""
    index = np.unique(np.linspace(0, sample.length - 1, steps).round().astype(int))
    return dataclasses.replace(sample, images=sample.images[index], T_world_camera=sample.T_world_camera[index],
                               poses=sample.poses[index], actions=sample.actions[index])


@pytest.fixture(scope="module")
def episodes():
    with Env(TINY) as env:
        return [record_expert(env, env_id, TINY) for env_id in (0, 1)]


@pytest.fixture(scope="module")
def batch(episodes):
    return collate([subsample(episodes[0][0], 8), subsample(episodes[1][0], 6)], VOCABULARY)


def seeded_model(kind: str, config: RunConfig = TINY, seed: int = 0):
    torch.manual_seed(seed)
    return build_model(kind, config, VOCABULARY)


def other_instruction(sample: EpisodeSample):
    """A different instruction in the same world: another landmark, another side."""
    index = (sample.instruction.landmark_index + 1) % len(sample.world.landmarks)
    side = SIDES[(SIDES.index(sample.instruction.side) + 1) % 4]
    return make_instruction(sample.world, index, side)


# -- data interface ---------------------------------------------------------------------------------------


def test_vocabulary_encodes_roundtrips_and_maps_unknown_words():
    v = VOCABULARY
    ids = v.encode("Go to the LEFT side of the red barrel!")
    assert v.decode(ids) == ["go", "to", "the", "left", "side", "of", "the", "red", "barrel"]
    assert v.encode("go to the zebra")[-1] == v.unk_id and v.encode("") == [v.unk_id]
    assert Vocabulary.from_json(v.to_json()) == v
    with pytest.raises(ValueError):
        Vocabulary.from_json('{"words": ["a", "b"]}')


def test_collate_pads_masks_and_carries_labels(episodes):
    a, b = subsample(episodes[0][0], 8), subsample(episodes[1][0], 5)
    batch = collate([a, b], VOCABULARY)
    assert batch.images.shape == (2, a.length, 144, 256, 3) and batch.images.dtype == torch.uint8
    assert batch.mask.tolist() == [[True] * a.length, [True] * b.length + [False] * (a.length - b.length)]
    assert batch.frames == a.length + b.length
    # Padding repeats the last real step, so padded camera poses stay invertible.
    assert torch.equal(batch.T_world_camera[1, -1], batch.T_world_camera[1, b.length - 1])
    assert torch.equal(batch.actions[1, :b.length], torch.from_numpy(b.actions))
    for i, s in enumerate((a, b)):
        ids = VOCABULARY.encode(s.instruction.text)
        assert batch.tokens[i, :len(ids)].tolist() == ids and batch.lengths[i] == len(ids)
        assert (batch.tokens[i, len(ids):] == VOCABULARY.pad_id).all()
        M = len(s.world.landmarks)
        assert batch.landmark_valid[i].sum() == M
        lm = s.world.landmarks[s.instruction.landmark_index]
        assert batch.named_class[i] == lm.class_id
        assert batch.landmark_xy[i, batch.named_landmark[i]].tolist() == pytest.approx([lm.x, lm.y])
        assert SIDES[batch.side[i]] == s.instruction.side
        assert batch.goal_xy[i].tolist() == pytest.approx([s.instruction.goal_x, s.instruction.goal_y])


def test_labels_follow_the_camera_and_the_world(batch, episodes):
    model = seeded_model("gsmn")
    labels = make_labels(batch, model.geometry, model.image_size)
    sample = subsample(episodes[0][0], 8)
    for t in range(sample.length):
        points = np.array([[lm.x, lm.y, 0.0] for lm in sample.world.landmarks])
        uv, depth = project_points(sample.K, sample.T_world_camera[t], points)
        expected = in_image(uv, depth, 256, 144)
        assert labels.visible[0, t, :len(points)].tolist() == expected.tolist()
    assert not labels.visible[1, ~batch.mask[1]].any()  # padded steps see nothing
    assert labels.is_named.sum(1).tolist() == [1, 1]
    row, col = labels.goal_cell_w[0].tolist()
    centre = model.geometry.world_cell_centres()[row, col]
    assert (centre - batch.goal_xy[0]).abs().max() <= model.geometry.cell_size / 2 + 1e-5


# -- shapes and purity -------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_output_shapes(batch, kind):
    model = seeded_model(kind)
    out = forward_batch(model, batch)
    B, T = batch.size, batch.steps
    assert out.features_c.shape == (B, T, 32, 18, 32)
    assert out.sentence_embedding.shape == (B, 30)
    for name in ("v", "omega", "stop_logit"):
        assert getattr(out, name).shape == (B, T)
    assert ((out.v >= 0) & (out.v <= 1)).all() and ((out.omega >= -1) & (out.omega <= 1)).all()
    if isinstance(out, GSMNOutputs):
        expected = {"projected_features_w": (32, 32, 32), "coverage_w": (1, 32, 32), "semantic_map_w": (32, 32, 32),
                    "relevance_map_w": (3, 32, 32), "relevance_map_r": (3, 64, 64), "goal_map_r": (2, 64, 64),
                    "goal_map_w": (2, 32, 32)}
        for name, shape in expected.items():
            assert getattr(out, name).shape == (B, T, *shape), name
        assert set(out.maps()) >= set(expected)
    else:
        assert out.relevance_map_c.shape == (B, T, 3, 18, 32) and out.goal_map_c.shape == (B, T, 2, 18, 32)
        assert (out.memory is None) == (kind == "gs-fpv")


@pytest.mark.parametrize("kind", ["gsmn", "gs-fpv-mem"])
def test_forward_does_not_modify_its_inputs(batch, kind):
    config = dataclasses.replace(TINY, model=dataclasses.replace(TINY.model, pose_noise_std=0.5,
                                                                 pose_noise_yaw_deg=2.0))
    model = seeded_model(kind, config)
    before = {f.name: getattr(batch, f.name).clone() for f in dataclasses.fields(batch)}
    forward_batch(model, batch, torch.Generator().manual_seed(0))
    for name, value in before.items():
        assert torch.equal(getattr(batch, name), value), name


def test_initial_sigmoid_kernels_are_uniform():
    """Language filters start N(0, 0.001): through the original's sigmoid every kernel starts close to uniform,
    whatever the instruction."""
    model = seeded_model("gsmn", SIGMOID)
    e = torch.randn(4, 30)
    k = model.relevance_filter.kernels(e)
    torch.testing.assert_close(k, torch.full_like(k, 1 / math.sqrt(96)), atol=0, rtol=0.03)
    k1, k2 = model.goal_filter.kernels(e)
    torch.testing.assert_close(k1, torch.full_like(k1, 1 / 9), atol=0, rtol=0.03)
    torch.testing.assert_close(k2, torch.full_like(k2, 1 / math.sqrt(54)), atol=0, rtol=0.03)


@pytest.mark.parametrize("kind", ["gsmn", "gs-fpv-mem"])
def test_signed_kernels_can_subtract_a_channel_and_stay_unit_norm(kind):
    """model.filter_activation = "none" (the paper's K = W e + b, the default): kernels take both signs, each still
    unit-norm; the original's sigmoid keeps every weight positive."""
    assert TINY.model.filter_activation == "none"
    e = torch.randn(4, 30)
    for config, can_be_negative in ((SIGMOID, False), (TINY, True)):
        model = seeded_model(kind, config)
        k = model.relevance_filter.kernels(e)
        k1, k2 = model.goal_filter.kernels(e)
        assert bool((k < 0).any()) == can_be_negative and bool((k1 < 0).any()) == can_be_negative
        torch.testing.assert_close(k.flatten(1).norm(dim=1), torch.ones(4))
        torch.testing.assert_close(k2.flatten(1).norm(dim=1), torch.ones(4))
    with pytest.raises(ValueError, match="filter_activation"):
        dataclasses.replace(TINY.model, filter_activation="relu")


@pytest.mark.slow
def test_bf16_inference_is_close_and_leaves_training_in_float32(batch):
    fp32 = seeded_model("gsmn")
    config = dataclasses.replace(TINY, model=dataclasses.replace(TINY.model, inference_bf16=True))
    bf16 = seeded_model("gsmn", config)
    with torch.inference_mode():
        a, b = forward_batch(fp32.eval(), batch), forward_batch(bf16.eval(), batch)
    assert b.features_c.dtype == torch.float32 and b.semantic_map_w.dtype == torch.float32
    assert (a.features_c - b.features_c).abs().mean() < 0.05
    torch.testing.assert_close(b.v, a.v, atol=0.02, rtol=0)
    fp32.train(), bf16.train()
    torch.manual_seed(0)
    a = forward_batch(fp32, batch)
    torch.manual_seed(0)
    b = forward_batch(bf16, batch)
    assert torch.equal(a.features_c, b.features_c)


# -- step-level pieces -------------------------------------------------------------------------------------


def test_grounding_a_new_instruction_on_a_stored_map_equals_a_full_forward(episodes):
    sample = subsample(episodes[0][0], 6)
    other = dataclasses.replace(sample, instruction=other_instruction(sample))
    model = seeded_model("gsmn").eval()
    with torch.inference_mode():
        first = forward_batch(model, collate([sample], VOCABULARY))
        full = forward_batch(model, collate([other], VOCABULARY))
        ids = VOCABULARY.encode(other.instruction.text)
        grounded = model.ground(first.semantic_map_w, first.poses, tokens=torch.tensor([ids]),
                                lengths=torch.tensor([len(ids)]))
        last = model.ground(first.semantic_map_w[:, -1], first.poses[:, -1], grounded.sentence_embedding)
    torch.testing.assert_close(first.semantic_map_w, full.semantic_map_w)  # the map ignores the instruction
    for name in ("relevance_map_w", "relevance_map_r", "goal_map_r", "goal_map_w", "v", "omega", "stop_logit"):
        torch.testing.assert_close(getattr(grounded, name), getattr(full, name), msg=name)
        torch.testing.assert_close(getattr(last, name), getattr(full, name)[:, -1], msg=name)
    assert not torch.allclose(first.relevance_map_w, full.relevance_map_w)


@pytest.mark.parametrize("kind", ["gsmn", "gs-fpv"])
def test_instruction_kernels_made_beforehand_change_nothing(episodes, kind):
    """The policy makes the language kernels once per episode; a step given them equals one that makes them."""
    sample = subsample(episodes[0][0], 3)
    b = collate([sample], VOCABULARY)
    model = seeded_model(kind).eval()
    with torch.inference_mode():
        e = model.encode_instruction(b.tokens, b.lengths)
        kernels = model.instruction_kernels(e)
        state_a = state_b = None
        for t in range(b.steps):
            args = (b.images[:, t], b.T_world_camera[:, t], b.K, b.poses[:, t], e)
            a, state_a = model.step(*args, state_a)
            c, state_b = model.step(*args, state_b, kernels=kernels)
            for name, value in a.maps().items():
                assert torch.equal(value, c.maps()[name]), name
            assert torch.equal(a.v, c.v) and torch.equal(a.omega, c.omega) and torch.equal(a.stop_logit, c.stop_logit)


@pytest.mark.parametrize("kind", ["gsmn", "gs-fpv-mem"])
def test_policy_step_by_step_equals_the_sequence_forward(episodes, kind):
    sample, observations, task = episodes[0]
    steps = 6
    model = seeded_model(kind)
    policy = ModelPolicy(model, VOCABULARY, TINY)
    policy.reset(task)
    records = []
    for obs in observations[:steps]:
        action = policy.act(obs)
        records.append((action, policy.last_outputs))
    short = dataclasses.replace(sample, images=sample.images[:steps], T_world_camera=sample.T_world_camera[:steps],
                                poses=sample.poses[:steps], actions=sample.actions[:steps])
    with torch.inference_mode():
        full = forward_batch(model, collate([short], VOCABULARY))
    # Batched and single-image convolutions take different oneDNN kernels: equal up to float rounding, which the
    # thirteen instance norms amplify to about 1e-4 on the unit-scale features.
    for t, (action, out) in enumerate(records):
        torch.testing.assert_close(out.v[0, 0], full.v[0, t], atol=1e-4, rtol=0)
        torch.testing.assert_close(out.omega[0, 0], full.omega[0, t], atol=1e-4, rtol=0)
        torch.testing.assert_close(out.stop_logit[0, 0], full.stop_logit[0, t], atol=1e-4, rtol=0)
        # The same 1e-4 in normalised units, scaled to m/s and rad/s.
        assert action.forward_velocity == pytest.approx(float(full.v[0, t]) * 1.6, abs=1.6e-4)
        assert action.yaw_rate == pytest.approx(float(full.omega[0, t]) * 2.44, abs=2.44e-4)
        assert action.stop == bool(full.stop_logit[0, t] > 0)
        if kind == "gsmn":
            torch.testing.assert_close(out.semantic_map_w[0, 0], full.semantic_map_w[0, t], atol=1e-3, rtol=0)
            torch.testing.assert_close(out.goal_map_w[0, 0], full.goal_map_w[0, t], atol=1e-3, rtol=0)
    assert policy.name == kind and policy.needs_images
    if kind == "gsmn":
        cf = policy.counterfactual(other_instruction(sample).text)
        assert cf.goal_map_w.shape == (1, 2, 32, 32)


# -- losses and gradients ----------------------------------------------------------------------------------


def losses_of(model, batch, config: LossConfig, seed: int = 0):
    torch.manual_seed(seed)  # dropout
    outputs = forward_batch(model, batch)
    return compute_losses(model, batch, outputs, config, generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("kind", KINDS)
def test_losses_are_finite_and_accuracies_reported(batch, kind):
    model = seeded_model(kind)
    result = losses_of(model, batch, LossConfig())
    assert torch.isfinite(result.total)
    assert set(result.terms) == set(TERMS)
    for name, value in result.terms.items():
        assert torch.isfinite(value) and value >= 0, name
    with_plan = kind == "gsmn"
    assert (result.terms["goal"] > 0) == with_plan
    for name in ("perception", "grounding", "instruction_landmark", "instruction_side", "stop"):
        assert 0 <= result.accuracies[name] <= 1, name
    assert math.isnan(result.accuracies["goal"]) != with_plan
    expected = sum(w * result.terms[k] for k, w in (("action", 1.0), ("perception", 0.1), ("language", 0.1),
                                                   ("grounding", 0.1), ("goal", 0.1 * with_plan)))
    torch.testing.assert_close(result.total, expected)


@pytest.mark.parametrize("switch", ["perception", "language", "grounding", "goal"])
def test_each_ablation_switch_zeroes_exactly_its_term(batch, switch):
    model = seeded_model("gsmn")
    full = losses_of(model, batch, LossConfig())
    ablated = losses_of(model, batch, dataclasses.replace(LossConfig(), **{switch: False}))
    assert ablated.terms[switch] == 0 and full.terms[switch] > 0
    for name in TERMS:
        if name != switch:
            torch.testing.assert_close(ablated.terms[name], full.terms[name], msg=name)
    torch.testing.assert_close(ablated.total, full.total - 0.1 * full.terms[switch])


def grads_of(model, batch, config: LossConfig) -> dict[str, torch.Tensor | None]:
    model.zero_grad(set_to_none=True)
    losses_of(model, batch, config).total.backward()
    return {name: p.grad for name, p in model.named_parameters()}


@pytest.mark.parametrize("kind", KINDS)
def test_gradients_reach_every_parameter(batch, kind):
    model = seeded_model(kind)
    grads = grads_of(model, batch, LossConfig())
    for name, g in grads.items():
        if kind == "gsmn-no-plan" and name.startswith("heads.goal."):
            assert g is None, name  # trained without J_plan
            continue
        assert g is not None and torch.isfinite(g).all(), name
        assert g.abs().sum() > 0, name


@pytest.mark.parametrize("switch, heads", [("perception", ["heads.perception."]), ("grounding", ["heads.grounding."]),
                                           ("language", ["heads.language_landmark.", "heads.language_side."]),
                                           ("goal", ["heads.goal."])])
def test_an_ablated_objective_trains_nothing_of_its_head(batch, switch, heads):
    model = seeded_model("gsmn")
    grads = grads_of(model, batch, dataclasses.replace(LossConfig(), **{switch: False}))
    for name, g in grads.items():
        if any(name.startswith(h) for h in heads):
            assert g is None, name
        else:
            assert g is not None, name


def test_pose_noise_moves_camera_and_pose_together():
    poses = torch.tensor([[[10.0, 5.0, 0.7], [12.0, 6.0, 0.9]]])
    T = torch.eye(4).repeat(1, 2, 1, 1)
    T[..., :3, 3] = torch.tensor([[[10.1, 5.05, 5.0], [12.1, 6.1, 5.0]]])
    noisy_poses, noisy_T = perturb_poses(poses, T, 0.5, 5.0, torch.Generator().manual_seed(0))
    assert not torch.equal(noisy_poses, poses) and torch.equal(T[..., 0, 0], torch.ones(1, 2))  # inputs untouched
    # The camera keeps its place relative to the drone, in the drone's (noisy) frame.
    def local(pose, Tm, t):
        d = Tm[0, t, :2, 3] - pose[0, t, :2]
        c, s = torch.cos(pose[0, t, 2]), torch.sin(pose[0, t, 2])
        return torch.stack([c * d[0] + s * d[1], -s * d[0] + c * d[1]])

    for t in range(2):
        torch.testing.assert_close(local(noisy_poses, noisy_T, t), local(poses, T, t), atol=1e-5, rtol=0)
    torch.testing.assert_close(invert_rigid(noisy_T) @ noisy_T, torch.eye(4).expand(1, 2, 4, 4), atol=1e-5, rtol=0)
    same, _ = perturb_poses(poses, T, 0.5, 5.0, torch.Generator().manual_seed(0))
    assert torch.equal(same, noisy_poses)
    assert perturb_poses(poses, T, 0.0, 0.0)[0] is poses


# -- checkpoints -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_checkpoint_round_trip_gives_identical_outputs(tmp_path, batch, kind):
    model = seeded_model(kind).eval()
    folder = save_checkpoint(tmp_path / "ckpt", model, TINY, VOCABULARY, {"metrics": {"success": 0.5}, "epoch": 3})
    assert sorted(p.name for p in folder.iterdir()) == sorted(
        ["weights.safetensors", "config.json", "vocabulary.json", "meta.json"])
    loaded, config, vocabulary, meta = load_checkpoint(folder)
    assert config == TINY and vocabulary == VOCABULARY and not loaded.training
    assert meta["kind"] == kind and meta["metrics"] == {"success": 0.5} and meta["epoch"] == 3
    assert meta["code_version"] and meta["created"]
    with torch.inference_mode():
        a, b = forward_batch(model, batch), forward_batch(loaded, batch)
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        assert (x is None and y is None) or torch.equal(x, y), f.name
    # Saving again replaces the checkpoint atomically, leaving no temporary folders behind.
    save_checkpoint(folder, loaded, TINY, VOCABULARY)
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt"]
    assert isinstance(load_policy(folder), ModelPolicy)


@pytest.mark.parametrize("removed", [("grounding_filter",), ("goal_filter",), ("grounding_filter", "goal_filter")])
@pytest.mark.slow
def test_a_removed_filter_is_the_original_codes_identity(tmp_path, batch, removed):
    """The original code's module ablations (docs/model.md, "Removing a module"): the maps form a stack, a removed
    filter passes it on, each reader takes its first channels; the removed filter has no weights, trains nothing,
    and the step-by-step policy and a checkpoint round trip compute what the sequence forward does."""
    config = dataclasses.replace(TINY, model=dataclasses.replace(TINY.model, **{name: False for name in removed}))
    model = seeded_model("gsmn", config).eval()
    with torch.inference_mode():
        out = forward_batch(model, batch)
    stack = out.semantic_map_w if "grounding_filter" in removed else torch.cat([out.relevance_map_w,
                                                                                 out.semantic_map_w], dim=2)
    torch.testing.assert_close(out.relevance_map_w, stack[:, :, :3])
    if "goal_filter" in removed:  # the controller reads [R, next 2 channels], and the record's goal maps are those
        torch.testing.assert_close(out.goal_map_w, stack[:, :, 3:5])
        assert model.goal_filter is None
    if "grounding_filter" in removed:
        assert model.relevance_filter is None
    names = {k.split(".")[0] for k in model.state_dict()}
    assert names.isdisjoint({"relevance_filter" if "grounding_filter" in removed else "", "goal_filter"
                             if "goal_filter" in removed else ""})
    folder = save_checkpoint(tmp_path / "ckpt", model, config, VOCABULARY)
    loaded, loaded_config, _, _ = load_checkpoint(folder)
    assert loaded_config.model == config.model
    with torch.inference_mode():
        again = forward_batch(loaded, batch)
    torch.testing.assert_close(again.v, out.v)
    torch.testing.assert_close(again.goal_map_r, out.goal_map_r)
    model.train()
    losses = compute_losses(model, batch, forward_batch(model, batch), config.loss)
    losses.total.backward()
    assert all(p.grad is not None for p in model.controller.parameters())


def test_a_checkpoint_from_before_filter_activation_loads_with_the_sigmoid(tmp_path, batch):
    """config.json files written before model.filter_activation existed used the sigmoid: they load as such and fly
    as they did."""
    model = seeded_model("gsmn", SIGMOID).eval()
    folder = save_checkpoint(tmp_path / "old", model, SIGMOID, VOCABULARY)
    raw = json.loads((folder / "config.json").read_text())
    del raw["model"]["filter_activation"]
    (folder / "config.json").write_text(json.dumps(raw))
    loaded, config, _, _ = load_checkpoint(folder)
    assert config == SIGMOID
    with torch.inference_mode():
        torch.testing.assert_close(forward_batch(loaded, batch).goal_map_w, forward_batch(model, batch).goal_map_w,
                                   rtol=0, atol=0)


def test_the_head_class_counts_are_the_catalogues_and_the_tasks():
    """ModelConfig carries the class counts so that the model need not import the catalogue; they cannot drift."""
    assert ModelConfig().landmark_classes == len(CATALOGUE) == 63
    assert ModelConfig().side_classes == len(SIDES)
    heads = seeded_model("gsmn").heads
    assert heads.perception.out_features == heads.language_landmark.out_features == len(CATALOGUE)
    assert heads.language_side.out_features == len(SIDES)


@pytest.mark.parametrize("name", sorted(CHECKPOINTS))
def test_the_shipped_checkpoints_load_without_the_class_count_fields(name):
    """checkpoints/*/config.json predate model.landmark_classes and model.side_classes: the defaults fill them."""
    folder = CHECKPOINTS[name]
    raw = json.loads((folder / "config.json").read_text())
    assert "landmark_classes" not in raw["model"] and "side_classes" not in raw["model"]
    model, config, _, meta = load_checkpoint(folder)
    assert meta["kind"] == name
    assert (config.model.landmark_classes, config.model.side_classes) == (len(CATALOGUE), len(SIDES))
    assert model.heads.perception.out_features == len(CATALOGUE)


def test_averaging_checkpoints_gives_the_mean_of_their_weights(tmp_path):
    a = save_checkpoint(tmp_path / "a", seeded_model("gsmn", seed=0), TINY, VOCABULARY)
    b = save_checkpoint(tmp_path / "b", seeded_model("gsmn", seed=1), TINY, VOCABULARY)
    mean = tmp_path / "mean"
    assert main(["average", str(a), str(b), "--out", str(mean)]) == 0  # `gsmn average`: average_checkpoints
    (wa, *_), (wb, *_), (wm, _, vocabulary, meta) = (load_checkpoint(f) for f in (a, b, mean))
    sa, sb, sm = wa.state_dict(), wb.state_dict(), wm.state_dict()
    assert any(not torch.equal(sa[k], sb[k]) for k in sa)
    for k in sm:
        torch.testing.assert_close(sm[k], (sa[k] + sb[k]) / 2, rtol=0, atol=1e-7)
    assert vocabulary == VOCABULARY and meta["averaged_from"] == [str(a), str(b)] and meta["metrics"] == {}
    assert not list(mean.glob("optimizer.*"))
    # Only one model's checkpoints average: another kind, or another model config, is refused by name.
    other = save_checkpoint(tmp_path / "fpv", seeded_model("gs-fpv"), TINY, VOCABULARY)
    sigmoid = save_checkpoint(tmp_path / "sigmoid", seeded_model("gsmn", SIGMOID), SIGMOID, VOCABULARY)
    for bad in (other, sigmoid):
        with pytest.raises(CheckpointError, match=f"{bad}.*differs"):
            average_checkpoints([a, bad], tmp_path / "bad")
        assert main(["average", str(a), str(bad), "--out", str(tmp_path / "bad")]) == 2
    assert not (tmp_path / "bad").exists()


def test_a_memory_baseline_warm_started_from_gs_fpv_flies_as_it_and_can_learn_to_use_its_memory(batch):
    """memory_from_fpv: GS-FPV-MEM made from a GS-FPV computes the same actions; the training loss
    reaches the perceptron's (zero) weights on the LSTM, so the memory can come to matter."""
    fpv = seeded_model("gs-fpv", seed=3).eval()
    mem = memory_from_fpv(fpv).eval()
    assert mem.kind == "gs-fpv-mem" and mem.memory is not None
    with torch.inference_mode():
        a, b = forward_batch(fpv, batch), forward_batch(mem, batch)
    assert b.memory.abs().max() > 0  # the LSTM runs; the perceptron ignores it
    for name in ("v", "omega", "stop_logit", "relevance_map_c", "goal_map_c"):
        torch.testing.assert_close(getattr(b, name), getattr(a, name), rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="needs a GS-FPV"):
        memory_from_fpv(mem)
    grads = grads_of(mem.train(), batch, LossConfig())
    n_in = fpv.perceptron.hidden.in_features
    on_memory = grads["perceptron.out.weight"][:, n_in:n_in + TINY.model.fpv_memory]
    assert on_memory.abs().sum() > 0


def test_keep_iterations_copies_each_new_checkpoint_once(tmp_path, monkeypatch):
    """keep_iteration (`gsmn keep-iterations`, run beside a training run) keeps RUN_itN per iteration, without the
    Adam state, and takes no copy of a checkpoint it already has or of one without an iteration."""
    from gsmn.model import checkpoint as keep

    run = tmp_path / "run"
    assert keep.keep_iteration(run) is None  # nothing written yet
    model = seeded_model("gsmn", seed=0)
    optimizer = torch.optim.Adam(model.parameters())
    save_checkpoint(run / "checkpoint", model, TINY, VOCABULARY, meta={"metrics": {}})
    assert keep.keep_iteration(run) is None  # a checkpoint that says no iteration
    for n, seed in ((1, 0), (2, 1)):
        model = seeded_model("gsmn", seed=seed)
        save_checkpoint(run / "checkpoint", model, TINY, VOCABULARY, meta={"metrics": {"iteration": n}},
                        optimizer_state=optimizer.state_dict())
        assert keep.keep_iteration(run) == tmp_path / f"run_it{n}"
        assert keep.keep_iteration(run) is None
        kept, *_ = load_checkpoint(tmp_path / f"run_it{n}")
        assert all(torch.equal(a, b) for a, b in zip(kept.state_dict().values(), model.state_dict().values(),
                                                     strict=True))
        assert not list((tmp_path / f"run_it{n}").glob("optimizer.*"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run", "run_it1", "run_it2"]
    # The run replaces its checkpoint (iteration 4) while iteration 3's is being copied: no copy is kept then,
    # and the next poll keeps iteration 4's.
    save_checkpoint(run / "checkpoint", model, TINY, VOCABULARY, meta={"metrics": {"iteration": 3}})
    copytree = keep.shutil.copytree

    def copy_during_replacement(src, dst, **kwargs):
        out = copytree(src, dst, **kwargs)
        save_checkpoint(run / "checkpoint", model, TINY, VOCABULARY, meta={"metrics": {"iteration": 4}})
        return out

    monkeypatch.setattr(keep.shutil, "copytree", copy_during_replacement)
    assert keep.keep_iteration(run) is None
    monkeypatch.undo()
    assert keep.keep_iteration(run) == tmp_path / "run_it4"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run", "run_it1", "run_it2", "run_it4"]


@pytest.fixture
def checkpoint(tmp_path):
    return save_checkpoint(tmp_path / "ckpt", seeded_model("gsmn"), TINY, VOCABULARY)


def test_missing_checkpoint_files_are_named(tmp_path, checkpoint):
    with pytest.raises(CheckpointError, match="no such folder"):
        load_checkpoint(tmp_path / "nowhere")
    for name in ("weights.safetensors", "config.json", "vocabulary.json", "meta.json"):
        (checkpoint / name).rename(tmp_path / name)
        with pytest.raises(CheckpointError, match=f"{checkpoint}.*{name}.*missing"):
            load_checkpoint(checkpoint)
        (tmp_path / name).rename(checkpoint / name)
    load_checkpoint(checkpoint)


def test_malformed_checkpoint_files_are_named(checkpoint):
    (checkpoint / "config.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="config.json is not valid JSON"):
        load_checkpoint(checkpoint)
    config = json.loads(TINY.to_json())
    config["model"]["no_such_field"] = 1
    (checkpoint / "config.json").write_text(json.dumps(config))
    with pytest.raises(CheckpointError, match="config.json is not a valid RunConfig.*no_such_field"):
        load_checkpoint(checkpoint)
    (checkpoint / "config.json").write_text(TINY.to_json())
    (checkpoint / "weights.safetensors").write_bytes(b"\x00" * 20)
    with pytest.raises(CheckpointError, match="weights.safetensors cannot be read"):
        load_checkpoint(checkpoint)


def test_weights_that_do_not_fit_are_refused(tmp_path, checkpoint):
    # Wrong shapes: the config says 16 feature channels, the weights have 32.
    config = json.loads(TINY.to_json())
    config["model"]["feature_channels"] = 16
    (checkpoint / "config.json").write_text(json.dumps(config))
    with pytest.raises(CheckpointError, match="does not fit a 'gsmn' model.*wrong shape.*resnet"):
        load_checkpoint(checkpoint)
    (checkpoint / "config.json").write_text(TINY.to_json())
    # Wrong kind: GSMN weights labelled as GS-FPV.
    meta = json.loads((checkpoint / "meta.json").read_text())
    (checkpoint / "meta.json").write_text(json.dumps({**meta, "kind": "gs-fpv"}))
    with pytest.raises(CheckpointError, match="does not fit a 'gs-fpv' model.*unexpected.*controller"):
        load_checkpoint(checkpoint)
    (checkpoint / "meta.json").write_text(json.dumps({**meta, "kind": "resnet50"}))
    with pytest.raises(CheckpointError, match="kind 'resnet50'"):
        load_checkpoint(checkpoint)


def test_the_kind_is_read_without_the_weights(tmp_path, checkpoint):
    (checkpoint / "weights.safetensors").unlink()  # the kind alone needs only meta.json
    assert read_checkpoint_kind(checkpoint) == "gsmn"
    with pytest.raises(CheckpointError, match="no such folder"):
        read_checkpoint_kind(tmp_path / "nowhere")
    (tmp_path / "data").mkdir()
    with pytest.raises(CheckpointError, match="meta.json is missing"):
        read_checkpoint_kind(tmp_path / "data")
    (checkpoint / "meta.json").write_text("[]")
    with pytest.raises(CheckpointError, match="meta.json must hold an object"):
        read_checkpoint_kind(checkpoint)
    (checkpoint / "meta.json").write_text("{}")
    with pytest.raises(CheckpointError, match="names kind None"):
        read_checkpoint_kind(checkpoint)


def test_save_refuses_a_config_that_does_not_describe_the_model(tmp_path):
    model = seeded_model("gs-fpv")
    other = dataclasses.replace(TINY, model=ModelConfig(feature_channels=16))
    with pytest.raises(ValueError, match="does not describe this model"):
        save_checkpoint(tmp_path / "x", model, other, VOCABULARY)
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "precious.txt").write_text("keep me")
    with pytest.raises(CheckpointError, match="not a checkpoint"):
        save_checkpoint(tmp_path / "data", model, TINY, VOCABULARY)
    assert (tmp_path / "data" / "precious.txt").exists()


def test_unknown_kind_is_refused():
    with pytest.raises(ValueError, match="unknown model kind"):
        build_model("gsmn-xl", TINY)


# -- learning ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["gsmn", "gs-fpv-mem"])
@pytest.mark.training
def test_a_few_steps_on_one_batch_reduce_the_loss(batch, kind):
    model = seeded_model(kind)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3, weight_decay=1e-7)
    model.eval()  # no dropout: measure the loss the same way before and after
    with torch.no_grad():
        before = losses_of(model, batch, LossConfig()).total.item()
    for step in range(12):
        model.train()
        optimizer.zero_grad()
        losses_of(model, batch, LossConfig(), seed=step).total.backward()
        optimizer.step()
    model.eval()
    with torch.no_grad():
        after = losses_of(model, batch, LossConfig()).total.item()
    assert after < 0.8 * before, (before, after)


def test_the_resnet_trains_in_nchw_on_the_cpu_and_infers_channels_last():
    """Its weights move to the mode's memory format (the same Parameters, so an optimizer goes on; never inference
    tensors, even for eval() under inference_mode); both formats compute the same features up to rounding."""
    from gsmn.model.perception import ResNet13, standardise

    torch.manual_seed(0)
    net = ResNet13()
    params = list(net.parameters())
    optimizer = torch.optim.Adam(params, lr=1e-3)
    images = standardise(torch.randint(0, 256, (2, 144, 256, 3), dtype=torch.uint8))
    assert net.conv.weight.is_contiguous() and net.memory_format() == torch.contiguous_format
    trained = net(images)
    trained.square().mean().backward()
    optimizer.step()
    with torch.inference_mode():
        net.eval()
        inferred = net(images)
    weight = net.blocks[0].conv1.weight
    assert weight.is_contiguous(memory_format=torch.channels_last) and not weight.is_inference()
    assert list(net.parameters()) == params and all(p is q for p, q in zip(net.parameters(), params, strict=True))
    net.train()
    assert weight.is_contiguous() and not weight.is_contiguous(memory_format=torch.channels_last)
    again = net(images)
    torch.testing.assert_close(again.detach(), inferred, atol=1e-3, rtol=1e-3)
    again.square().mean().backward()  # the optimizer still holds the parameters the model uses
    before = weight.detach().clone()
    optimizer.step()
    assert not torch.equal(before, weight.detach())
    assert not ResNet13(channels_last=False).eval().conv.weight.is_contiguous(memory_format=torch.channels_last)


@pytest.mark.parametrize("stride", [1, 2])
@pytest.mark.parametrize("channels_last", [False, True])
def test_the_pooled_skip_is_avg_pool2d_with_or_without_gradients(stride, channels_last):
    """The residual blocks' 3x3 AvgPool skip (a depthwise convolution where autograd tracks it, avg_pool2d where
    not) gives AvgPool2d(3, stride, padding 1)'s values and input gradient, odd sizes and channels-last included."""
    from gsmn.model.blocks import AvgPool3x3

    torch.manual_seed(0)
    x = torch.randn(3, 5, 9, 12)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    reference = torch.nn.AvgPool2d(3, stride=stride, padding=1)
    pool = AvgPool3x3(stride)
    with torch.no_grad():
        torch.testing.assert_close(pool(x), reference(x), rtol=0, atol=0)  # the same kernel when no gradient
    a, b = x.clone().requires_grad_(), x.clone().requires_grad_()
    out, expected = pool(a), reference(b)
    assert out.grad_fn is not None and "Convolution" in type(out.grad_fn).__name__  # the faster path trains
    torch.testing.assert_close(out, expected, rtol=1e-5, atol=1e-6)
    grad = torch.randn_like(expected)
    out.backward(grad)
    expected.backward(grad)
    torch.testing.assert_close(a.grad, b.grad, rtol=1e-5, atol=1e-6)


def test_the_torch_threads_a_process_asks_for_are_capped_by_gsmn_max_threads(monkeypatch):
    from gsmn.model.runtime import set_torch_threads

    before = torch.get_num_threads()
    try:
        monkeypatch.setenv("GSMN_MAX_THREADS", "1")
        assert set_torch_threads(2) == 1 == torch.get_num_threads()
        monkeypatch.setenv("GSMN_MAX_THREADS", "4")
        assert set_torch_threads(2) == 2 == torch.get_num_threads()
        monkeypatch.delenv("GSMN_MAX_THREADS")
        assert set_torch_threads(3) == 3 == torch.get_num_threads()
        for bad in ("0", "two", "-1"):
            monkeypatch.setenv("GSMN_MAX_THREADS", bad)
            with pytest.raises(ValueError, match="GSMN_MAX_THREADS must be a positive integer"):
                set_torch_threads(1)
    finally:
        torch.set_num_threads(before)
