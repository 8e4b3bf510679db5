"""Dashboard units without a simulator: colours and legends, map layers and their orientation, the episode store,
the success quadrant drawn on the ground, and the text the page shows."""

from __future__ import annotations

import base64
import dataclasses
import math
import re

import numpy as np
import pytest

from app.live.models import MapHeads
from app.live.recording import FINISHED, QUEUED, RUNNING, Episode, EpisodeResult, EpisodeStore, jpeg_bytes
from app.page.scene import LABEL_GAP, boxes_overlap, label_box, label_heights, quadrant_angles
from app.render.colors import (
    UNSEEN_RGB,
    apply_colormap,
    class_palette,
    colorbar_html,
    decode_image,
    png_bytes,
    semantic_classes,
    semantic_legend_html,
    semantic_rgb,
    upscale,
    with_alpha,
)
from app.render.layers import build_layers, inspect_cell
from app.render.panels import (
    camera_html,
    cell_marks_html,
    inspector_markdown,
    maps_html,
    other_side,
    readout_markdown,
    result_markdown,
    status_line,
    timeline_marks,
)
from gsmn.config import preset
from gsmn.model.grid import world_cell
from gsmn.model.heads import positive_probability
from gsmn.task.instructions import SIDES, make_instruction
from gsmn.task.metrics import side_of
from gsmn.task.rollout import Task
from gsmn.world.landmarks import CATALOGUE
from gsmn.world.spec import split_env_ids, world_for_env

pytestmark = pytest.mark.unit


def test_colormap_spans_its_range_and_clips():
    values = np.array([[-1.0, 0.0, 0.5, 1.0, 2.0, np.nan]])
    rgb = apply_colormap(values, 0.0, 1.0)
    assert rgb.shape == (1, 6, 3) and rgb.dtype == np.uint8
    assert (rgb[0, 0] == rgb[0, 1]).all() and (rgb[0, 3] == rgb[0, 4]).all()  # clipped to the ends
    assert tuple(rgb[0, 1]) == (68, 1, 84) and tuple(rgb[0, 3]) == (253, 231, 37)  # viridis ends
    assert (rgb[0, 5] == rgb[0, 1]).all()  # NaN shows as the low end
    # viridis gets brighter monotonically: a person can read order from it
    ramp = apply_colormap(np.linspace(0, 1, 50)[None], 0, 1)[0].astype(float)
    luminance = ramp @ np.array([0.2126, 0.7152, 0.0722])
    assert (np.diff(luminance) >= -1e-9).all()
    bar = colorbar_html(0.0, 1.0, label="P(goal)")
    assert "0.00" in bar and "1.00" in bar and "P(goal)" in bar and "linear-gradient" in bar


def test_class_palette_is_distinct():
    palette = class_palette(len(CATALOGUE)).astype(int)
    assert palette.shape == (63, 3)
    distances = np.abs(palette[:, None] - palette[None]).sum(-1) + np.eye(63, dtype=int) * 999
    assert distances.min() >= 12  # no two classes share (nearly) one colour


def test_semantic_classes_pick_the_head_argmax_and_mark_unseen_cells():
    C, K = 4, 3
    weight = np.zeros((K, C), np.float32)
    weight[0, 0] = weight[1, 1] = weight[2, 2] = 5.0
    semantic = np.zeros((C, 2, 3), np.float16)
    semantic[0, 0, 0] = 1.0  # class 0
    semantic[1, 0, 1] = 1.0  # class 1
    semantic[2, 1, 2] = 1.0  # class 2; the rest never observed (exactly zero)
    classes, confidence, observed = semantic_classes(semantic, weight, np.zeros(K, np.float32))
    assert classes[0, 0] == 0 and classes[0, 1] == 1 and classes[1, 2] == 2
    assert observed.tolist() == [[True, True, False], [False, False, True]]
    assert confidence[0, 0] > 0.9
    palette = class_palette(K)
    rgb = semantic_rgb(classes, confidence, observed, palette)
    assert tuple(rgb[0, 2]) == UNSEEN_RGB
    assert (rgb[0, 0] <= palette[0]).all() and rgb[0, 0].sum() > 0.9 * palette[0].sum()  # sure: near full colour
    legend = semantic_legend_html(classes, observed, palette, ["tree", "barrel", "box"])
    assert "tree" in legend and "barrel" in legend and "box" in legend and "not seen" in legend


def test_upscale_keeps_cells_sharp_and_png_round_trips():
    cells = np.arange(12, dtype=np.uint8).reshape(2, 2, 3) * 20
    big = upscale(cells, 4)
    assert big.shape == (8, 8, 3)
    assert (big[:4, :4] == cells[0, 0]).all() and (big[4:, 4:] == cells[1, 1]).all()
    assert (decode_image(png_bytes(big)) == big).all()  # PNG: lossless, no smearing of categorical maps
    rgba = with_alpha(big, 0.5)
    assert rgba.shape == (8, 8, 4) and (rgba[..., 3] == 128).all()
    photo = (np.random.default_rng(0).random((144, 256, 3)) * 255).astype(np.uint8)
    assert decode_image(jpeg_bytes(photo)).shape == (144, 256, 3)


def _heads(C: int = 32) -> MapHeads:
    rng = np.random.default_rng(0)
    return MapHeads(rng.normal(size=(63, C)).astype(np.float32), np.zeros(63, np.float32),
                    np.array([[0, 0, 0], [1, 0, 0]], np.float32), np.zeros(2, np.float32),
                    np.array([[0, 0], [1, 0]], np.float32), np.zeros(2, np.float32),
                    class_names=tuple(m.noun_phrase for m in CATALOGUE))


def test_a_model_without_a_trained_goal_head_shows_no_p_goal():
    """Trained without J_plan, the goal head is its initialisation: the goal layers show channel 0, labelled so,
    and the cell inspector gives no P(goal)."""
    heads = dataclasses.replace(_heads(), goal_trained=False)
    semantic = np.full((32, 32, 32), 0.1, np.float16)
    relevance = np.zeros((3, 32, 32), np.float32)
    goal = np.zeros((2, 32, 32), np.float32)
    goal[0, 3, 4], goal[1, 3, 4] = 7.0, -50.0  # a trained head [[0,0],[1,0]] would give P(goal) 1 there
    goal_r = np.zeros((2, 64, 64), np.float32)
    layers = build_layers(semantic, relevance, goal, goal_r, heads, "probability", "fixed")
    assert layers["goal"].values[3, 4] == 7.0 and layers["goal"].values.max() == 7.0
    assert "J_plan" in layers["goal"].legend_html and "J_plan" in layers["goal_robot"].legend_html
    assert "P(goal)" not in layers["goal"].title and "J_plan" in layers["goal"].title
    world = world_for_env(70, preset("tiny").world)
    report = inspect_cell(world.landmarks[0].x, world.landmarks[0].y, semantic, relevance, goal, heads, world)
    assert math.isnan(report.p_goal)
    assert "no P(goal)" in inspector_markdown(report, 0)


def test_a_model_without_trained_perception_or_grounding_heads_shows_its_maps_themselves():
    """Trained without J_ground, the relevance layer shows the relevance map's three channels as red, green and blue
    (each scaled to its range over seen cells) and the inspector gives the channels instead of a P(named); without
    J_percept, the semantic layer shows the semantic map's main components and the inspector no landmark classes."""
    semantic = np.full((32, 32, 32), 0.1, np.float16)
    semantic[0, 5, 6] = 3.0
    relevance = np.zeros((3, 32, 32), np.float32)
    relevance[0, 5, 6], relevance[1, 5, 6] = 9.0, -40.0
    goal, goal_r = np.zeros((2, 32, 32), np.float32), np.zeros((2, 64, 64), np.float32)
    world = world_for_env(70, preset("tiny").world)
    x, y = world.landmarks[0].x, world.landmarks[0].y

    no_ground = dataclasses.replace(_heads(), grounding_trained=False)
    relevance[2, 7, 8] = 2.0  # the named landmark, say, in channel 2 alone
    layers = build_layers(semantic, relevance, goal, goal_r, no_ground, "probability", "fixed")
    rgb, alpha = layers["relevance"].rgb, layers["relevance"].alpha
    assert tuple(rgb[5, 6]) == (255, 0, 0) and tuple(rgb[7, 8]) == (0, 255, 255)  # ch 1 is lowest at (5, 6) alone
    assert tuple(rgb[0, 0]) == (0, 255, 0) and alpha[7, 8] == 1.0
    assert "J_ground" in layers["relevance"].title and layers["relevance"].values is None
    assert "J_ground" in layers["relevance"].legend_html and "channel 2" in layers["relevance"].legend_html
    assert "P(goal)" in layers["goal"].legend_html
    semantic_unseen = semantic.copy()
    semantic_unseen[:, 7:] = 0  # cells never seen neither show nor set a channel's range
    layers = build_layers(semantic_unseen, relevance, goal, goal_r, no_ground, "probability", "fixed")
    assert layers["relevance"].alpha[7, 8] == 0.0 and tuple(layers["relevance"].rgb[5, 6]) == (255, 0, 0)
    assert tuple(layers["relevance"].rgb[0, 0]) == (0, 255, 0)  # channel 2 is flat over seen cells: all zero
    report = inspect_cell(x, y, semantic, relevance, goal, no_ground, world)
    assert math.isnan(report.p_named) and report.classes and len(report.relevance) == 3
    assert "no P(named)" in inspector_markdown(report, 0) and "relevance channels" in inspector_markdown(report, 0)

    no_percept = dataclasses.replace(_heads(), perception_trained=False)
    layers = build_layers(semantic, relevance, goal, goal_r, no_percept, "probability", "fixed")
    assert tuple(layers["semantic"].rgb[5, 6]) == (255, 0, 0) and tuple(layers["semantic"].rgb[0, 0]) == (0, 0, 0)
    assert "J_percept" in layers["semantic"].title and "component 1" in layers["semantic"].legend_html
    assert "P(named)" in layers["relevance"].legend_html
    report = inspect_cell(x, y, semantic, relevance, goal, no_percept, world)
    assert report.classes == () and "J_percept" in inspector_markdown(report, 0)
    trained = build_layers(semantic, relevance, goal, goal_r, _heads(), "probability", "fixed")
    assert trained["semantic"].title == "Semantic map: most likely landmark" and "J_" not in trained["relevance"].title


def test_a_model_without_a_filter_says_so_in_its_panel():
    """The original code's module ablations (no grounding filter, no goal filter): the layer's title says plainly
    that the map does not exist and what is shown in its place, the semantic channels the next stage reads."""
    semantic = np.full((32, 32, 32), 0.1, np.float16)
    relevance, goal = np.zeros((3, 32, 32), np.float32), np.zeros((2, 32, 32), np.float32)
    goal_r = np.zeros((2, 64, 64), np.float32)
    no_ground = dataclasses.replace(_heads(), grounding_trained=False, grounding_filter=False)
    title = build_layers(semantic, relevance, goal, goal_r, no_ground)["relevance"].title
    assert title.startswith("No relevance map: this model has no grounding filter") and "channels 0, 1, 2" in title
    no_goal = dataclasses.replace(_heads(), goal_trained=False, goal_filter=False)
    layers = build_layers(semantic, relevance, goal, goal_r, no_goal)
    assert layers["goal"].title.startswith("No goal map: this model has no goal filter")
    assert "semantic channel 0" in layers["goal"].title and "P(named)" in layers["relevance"].legend_html
    neither = dataclasses.replace(no_goal, grounding_trained=False, grounding_filter=False)
    assert "semantic channel 3" in build_layers(semantic, relevance, goal, goal_r, neither)["goal"].title
    # a model that only lacks the objective keeps its filter: the title speaks of the head, not of a missing map
    no_objective = dataclasses.replace(_heads(), goal_trained=False)
    assert not build_layers(semantic, relevance, goal, goal_r, no_objective)["goal"].title.startswith("No goal map")


def test_went_wrong_leaves_out_the_figures_of_untrained_heads():
    """An untrained head's figure is None at every step, which first_failures reads as wrong from step 0: the
    dashboard's "went wrong" must leave it out instead."""
    from app.render.truth import went_wrong
    from gsmn.analysis.truth import Agreement

    figures = [Agreement(0.9, None, 0.5, 3), Agreement(0.9, None, 0.5, 3)]
    assert went_wrong(figures)["relevance"] == 0  # read without knowing the heads
    assert set(went_wrong(figures, dataclasses.replace(_heads(), grounding_trained=False))) == {"perception", "goal"}
    assert set(went_wrong(figures, dataclasses.replace(_heads(), perception_trained=False))) == {"relevance", "goal"}
    assert set(went_wrong(figures, dataclasses.replace(_heads(), goal_trained=False))) == {"perception", "relevance"}
    assert set(went_wrong([Agreement(0.9, 0.9, None, 3)])) == {"perception", "relevance"}  # older: goal all None


def test_positive_probability_is_the_binary_head_softmax():
    maps = np.zeros((3, 2, 2), np.float32)
    maps[0, 0, 0] = 10.0
    p = positive_probability(maps, np.array([[0, 0, 0], [1, 0, 0]], np.float32), np.zeros(2, np.float32))
    assert p[0, 0] > 0.99 and abs(p[1, 1] - 0.5) < 1e-6


def test_layers_keep_the_north_up_layout():
    """A value at row 0, column 31 of a world map is the north-east corner: it must stay there in every layer."""
    heads = _heads()
    semantic = np.zeros((32, 32, 32), np.float16)
    semantic[:, :, :] = 0.1
    relevance = np.zeros((3, 32, 32), np.float32)
    relevance[0, 0, 31] = 10.0  # the north-east cell
    goal = np.zeros((2, 32, 32), np.float32)
    goal[0, 0, 31] = 10.0
    goal_r = np.zeros((2, 64, 64), np.float32)
    goal_r[0, 0, 32] = 10.0  # straight ahead, at the far edge
    for range_mode in ("fixed", "frame"):
        layers = build_layers(semantic, relevance, goal, goal_r, heads, "probability", range_mode)
        assert set(layers) == {"semantic", "relevance", "goal", "goal_robot"}
        for name in ("relevance", "goal"):
            values = layers[name].values
            assert np.unravel_index(values.argmax(), values.shape) == (0, 31)
            assert layers[name].rgb.shape == (32, 32, 3)
            # the ground overlay is most opaque where the map is high
            assert layers[name].alpha[0, 31] == layers[name].alpha.max()
        assert np.unravel_index(layers["goal_robot"].values.argmax(), (64, 64)) == (0, 32)
    raw = build_layers(semantic, relevance, goal, goal_r, heads, "raw", "frame")
    assert raw["goal"].values[0, 31] == 10.0
    with pytest.raises(ValueError, match="value_mode"):
        build_layers(semantic, relevance, goal, goal_r, heads, "nonsense")


def test_world_cell_matches_the_model_layout():
    # docs/model.md: cell (r, c) is centred at x = (c + 0.5) s, y = 30 - (r + 0.5) s with s = 0.9375 m
    s = 30 / 32
    for r, c in [(0, 0), (0, 31), (31, 0), (17, 5)]:
        assert world_cell((c + 0.5) * s, 30 - (r + 0.5) * s, 30.0, 32) == (r, c)
    # the page outlines cells over the map in percent of its size; cells outside the map are left out
    marks = cell_marks_html([(0, 1, (255, 0, 0)), (5, 5, (1, 1, 1))], 2)
    assert marks.count("<div") == 1 and "left:50.000%;top:0.000%;width:50.000%" in marks and "rgb(255,0,0)" in marks


def test_episode_store_drops_the_oldest_finished_only():
    store = EpisodeStore(limit=2)
    world = world_for_env(70)
    task = Task(world, make_instruction(world, 0, "left"), np.zeros((2, 2)))
    episodes = []
    for status in (FINISHED, RUNNING, QUEUED, FINISHED):
        e = Episode(id=store.new_id(), task=task, policy="expert", system="oracle", checkpoint=None, horizon=150,
                    status=status)
        episodes.append(e)
        store.add(e)
    ids = [e.id for e in store.all()]
    assert episodes[0].id not in ids  # finished and oldest: dropped
    assert episodes[1].id in ids and episodes[2].id in ids  # live ones are never dropped
    assert store.get(12345) is None
    with pytest.raises(ValueError):
        EpisodeStore(limit=0)


def test_the_drawn_quadrant_is_the_one_the_metric_accepts():
    world = world_for_env(70)
    for index in range(len(world.landmarks)):
        for side in SIDES:
            instruction = make_instruction(world, index, side)
            a0, a1 = quadrant_angles(world, instruction)
            lm = world.landmarks[index]
            middle = (a0 + a1) / 2
            assert math.isclose(a1 - a0, math.pi / 2)
            for angle in (middle, a0 + 0.05, a1 - 0.05):
                point = (lm.x + 3 * math.cos(angle), lm.y + 3 * math.sin(angle))
                assert side_of((lm.x, lm.y), world.start_position, point) == side
            # the goal lies on the drawn quadrant's bisector
            goal_angle = math.atan2(instruction.goal_y - lm.y, instruction.goal_x - lm.x)
            assert math.isclose(math.cos(goal_angle - middle), 1.0, abs_tol=1e-9)


def test_landmark_labels_do_not_overlap_from_the_first_camera():
    """Some labels sit on each other at their natural heights (in env 84 the tower's and the tire stack's, seen from
    the first camera); raised, no two labels of the first 100 test worlds overlap as the 3D view first shows them,
    and none is lowered."""
    from gsmn.world.assets import load_catalogue

    top_of = {m.name: m.height for m in load_catalogue()}
    clashes = 0
    for env_id in split_env_ids("test", 100):
        world = world_for_env(env_id)
        tops = [(lm.x, lm.y, top_of[lm.model] * lm.scale) for lm in world.landmarks]
        texts = [lm.noun_phrase for lm in world.landmarks]
        heights = label_heights(tops, texts)
        boxes = [label_box((x, y, z), t) for (x, y, _), z, t in zip(tops, heights, texts, strict=True)]
        assert all(z >= top + LABEL_GAP - 1e-9 for (_, _, top), z in zip(tops, heights, strict=True))
        assert not any(boxes_overlap(a, b) for i, a in enumerate(boxes) for b in boxes[i + 1:]), env_id
        natural = [label_box((x, y, top + LABEL_GAP), t) for (x, y, top), t in zip(tops, texts, strict=True)]
        if any(boxes_overlap(a, b) for i, a in enumerate(natural) for b in natural[i + 1:]):
            clashes += 1
            assert any(z > top + LABEL_GAP for (_, _, top), z in zip(tops, heights, strict=True))  # one rose
    assert clashes > 0  # the test sees the case it is about


def _episode_with_steps() -> Episode:
    from app.live.recording import StepMaps, StepRecord
    from gsmn.task.rollout import EpisodeRecord

    world = world_for_env(70, preset("tiny").world)
    instruction = make_instruction(world, 0, "left")
    e = Episode(id=7, task=Task(world, instruction, np.zeros((2, 2))), policy="model", system="gsmn",
                checkpoint="ckpt", horizon=150, status=FINISHED)
    maps = StepMaps({"semantic_map_w": np.zeros((32, 32, 32), np.float16),
                     "coverage_w": np.zeros((1, 32, 32), np.float16),
                     "relevance_map_w": np.zeros((3, 32, 32), np.float16),
                     "goal_map_w": np.zeros((2, 32, 32), np.float16),
                     "goal_map_r": np.zeros((2, 64, 64), np.float16)}, np.zeros(3, np.float32), 1.2, -0.3, 0.7)
    e.steps.append(StepRecord(0, 0.0, (30.0, 0.0, 5.0), 2.3, np.eye(4, dtype=np.float32), b"", 1.2, -0.3, True,
                              maps))
    record = EpisodeRecord(system="gsmn", env_id=70, instruction=instruction.text, landmark_index=0,
                           noun_phrase=instruction.noun_phrase, side="left", ambiguous=False,
                           goal_x=instruction.goal_x, goal_y=instruction.goal_y, landmark_x=world.landmarks[0].x,
                           landmark_y=world.landmarks[0].y, start_x=world.start_x, start_y=world.start_y,
                           final_x=30.0, final_y=0.0, steps=0, stopped=True, success=False, landmark_success=False,
                           goal_distance=12.5, trajectory=(), actions=())
    e.result = EpisodeResult.of(record, 0.7)
    return e


def test_a_failure_says_whether_it_flew_through_the_success_region():
    """The episode's one step is at the start: never entered. Steps added at the goal (inside the left quadrant)
    and away from it are reported as spans with the highest P(stop) there; a success has no such row."""
    from dataclasses import replace

    e = _episode_with_steps()
    assert "| success region | never entered |" in result_markdown(e)
    first = e.steps[0] = replace(e.steps[0], maps=replace(e.steps[0].maps, stop_probability=0.1))
    goal = (e.task.instruction.goal_x, e.task.instruction.goal_y, 5.0)
    for i, (position, p) in enumerate([(goal, 0.2), (goal, 0.35), (first.position, 0.9), (goal, 0.1)], start=1):
        e.steps.append(replace(first, step=i, position=position, stop=False, maps=replace(first.maps,
                                                                                         stop_probability=p)))
    text = result_markdown(e)
    assert "flew through it at steps 1-2, 4 without a STOP there; highest P(stop) there **0.35**" in text
    assert "success region" not in result_markdown(replace(e, result=replace(e.result, success=True)))
    # the timeline marks the first step inside the region and the first step past P(stop) 0.5 after the start
    assert timeline_marks(e) == ((0, "0"), (1, "in region"), (3, "P(stop)>0.5"), (4, "4"))
    # marks closer than 8 % of the timeline share a label; an end beside one loses its number, not its tick
    away = [replace(first, step=i, position=first.position) for i in range(1, 28)]
    late = _episode_with_steps()
    late.steps[:] = [first, *away, replace(first, step=28, position=goal), replace(first, step=29, position=goal)]
    assert timeline_marks(late) == ((0, "0"), (28, "in region"), (29, None))
    late.steps[28] = replace(late.steps[28], maps=replace(first.maps, stop_probability=0.6))
    assert timeline_marks(late) == ((0, "0"), (28, "in region, P(stop)>0.5"), (29, None))
    late.steps[27] = replace(late.steps[27], maps=replace(first.maps, stop_probability=0.6))
    assert timeline_marks(late) == ((0, "0"), (27, "P(stop)>0.5, in region"), (28, None), (29, None))


def test_an_ambiguous_instruction_is_said_to_be_one():
    """Where the noun phrase names several landmarks of the world, the status and the result say how many and that
    only the ringed one is the goal; an unambiguous instruction gets no such note."""
    world = next(w for w in (world_for_env(i, preset("tiny").world) for i in range(70, 400))
                 if any(len(w.landmarks_named(lm.noun_phrase)) > 1 for lm in w.landmarks))
    index = next(i for i, lm in enumerate(world.landmarks) if len(world.landmarks_named(lm.noun_phrase)) > 1)
    n = len(world.landmarks_named(world.landmarks[index].noun_phrase))
    e = _episode_with_steps()
    e.task = Task(world, make_instruction(world, index, "left"), np.zeros((2, 2)))
    note = f"Ambiguous: {n} landmarks here are called"
    assert note in status_line(e) and note in result_markdown(e)
    unique = next(i for i, lm in enumerate(world.landmarks) if len(world.landmarks_named(lm.noun_phrase)) == 1)
    e.task = Task(world, make_instruction(world, unique, "left"), np.zeros((2, 2)))
    assert "Ambiguous" not in status_line(e) and "Ambiguous" not in result_markdown(e)


def test_the_page_text_says_the_result_plainly():
    e = _episode_with_steps()
    text = result_markdown(e)
    assert "Failure" in text and "12.5 m" in text and "said STOP after **0** steps" in text
    assert "asked **left**" in text and "0.70" in text
    readout = readout_markdown(e, 0, None, None)
    assert "Step 0" in readout and "P(stop) 0.70" in readout and "STOP" in readout
    assert other_side("go to the left side of the barrel", "left") == "go to the right side of the barrel"
    layers = build_layers(*(getattr(e.steps[0].maps, k) for k in ("semantic_w", "relevance_w", "goal_w", "goal_r")),
                          _heads())
    page = maps_html(e, 0, layers, None, lambda x, y: world_cell(x, y, 30.0, 32))
    assert 'data-episode="7"' in page and 'data-step="0"' in page and page.count("data:image/png;base64,") == 4
    assert "image-rendering:pixelated" in page  # one pixel per cell, scaled up sharp by the browser
    for uri in re.findall(r'src="data:image/png;base64,([^"]+)"', page):
        assert decode_image(base64.b64decode(uri)).shape[:2] in ((32, 32), (64, 64))
    assert page.count("box-shadow:inset") == 0  # the drone and the goal lie just outside the field here
    inside = maps_html(e, 0, layers, None, lambda x, y: (3, 4))
    assert inside.count("box-shadow:inset") == 2 * 3  # the drone's and the goal's cells on the three world maps
    camera = camera_html(jpeg_bytes(np.zeros((144, 256, 3), np.uint8)))
    assert '<img class="gsmn-camera" src="data:image/jpeg;base64,' in camera and "pixelated" in camera
    assert "No model maps" in maps_html(e, 0, None, None, None)


def test_every_map_of_the_output_record_is_a_layer_and_a_panel():
    """The layers come from the model's output record (GSMNOutputs.maps()): a map the heads do not read, or one
    added to the record later, is a layer and a panel of its own with no change to the dashboard."""
    from app.render.layers import LAYERS, map_layers
    from gsmn.model.gsmn import GSMNOutputs

    kept = {f.name for f in dataclasses.fields(GSMNOutputs)} & {"coverage_w", "relevance_map_r"}
    assert kept == {"coverage_w", "relevance_map_r"} and kept <= set(LAYERS)
    assert LAYERS[:4] == ("semantic", "relevance", "goal", "goal_robot")
    e = _episode_with_steps()
    elevation = np.zeros((1, 32, 32), np.float16)
    elevation[0, 0, 31] = 3.0
    maps = {**e.steps[0].maps.maps, "elevation_map_w": elevation, "relevance_map_r": np.ones((3, 64, 64), np.float16)}
    layers = map_layers(maps, _heads())
    assert list(layers) == ["semantic", "relevance", "goal", "goal_robot", "coverage_w", "elevation_map_w",
                            "relevance_map_r"]
    new = layers["elevation_map_w"]
    assert new.frame == "world" and new.title == "Elevation map, world frame" and new.values[0, 31] == 3.0
    assert layers["relevance_map_r"].frame == "robot" and layers["goal_robot"].frame == "robot"
    page = maps_html(e, 0, layers, None, lambda x, y: (3, 4))
    assert page.count("data:image/png;base64,") == 7 and 'data-layer="elevation_map_w"' in page
    assert page.count("box-shadow:inset") == 2 * 5  # the drone's and the goal's cells on the five world maps


def test_the_page_text_a_newcomer_reads():
    """Issue 51, items 5, 6, 7, 9, 12 and 16, as the page's pure text functions say them."""
    from dataclasses import replace

    from app.render.colors import OTHER_RGB
    from app.render.panels import (
        actions_data,
        compose_instruction,
        marks_clash,
        parse_env_id,
        suggestions,
        which_landmark,
        world_summary,
    )
    from gsmn.task.understand import parse_instruction

    # 6: the count matches the names (environment 76 has two palm trees; 0 two rocks)
    tiny = preset("tiny").world
    assert world_summary(world_for_env(76, tiny)) == "7 landmarks: box, cone, 2 palm trees, pyramid, rock, tent"
    for env_id in (0, 70, 72, 76):
        world = world_for_env(env_id, tiny)
        text = world_summary(world).split(": ", 1)[1]
        named = sum(int(part.split(" ", 1)[0]) if part[0].isdigit() else 1 for part in text.split(", "))
        assert named == len(world.landmarks) and world_summary(world).startswith(f"{len(world.landmarks)} landmarks")
    # 7: an ambiguous name says which one it means
    world = world_for_env(76, tiny)
    instruction = parse_instruction("go to the right side of the palm tree", world)
    lm = world.landmarks[instruction.landmark_index]
    assert instruction.ambiguous and f"x {lm.x:.0f} m, y {lm.y:.0f} m" in which_landmark(world, instruction)
    # 5: the legend lists only this world's landmarks, one entry per name, and names the grey only with a swatch
    heads = _heads()
    semantic = np.random.default_rng(1).normal(size=(32, 32, 32)).astype(np.float16)
    semantic[:, :4] = 0  # four rows never seen
    zeros = (np.zeros((3, 32, 32), np.float32), np.zeros((2, 32, 32), np.float32), np.zeros((2, 64, 64), np.float32))
    names = tuple(lm.noun_phrase for lm in world_for_env(72, tiny).landmarks)
    layer = build_layers(semantic, *zeros, heads, world_names=names)["semantic"]
    listed = [n for n in re.findall(r"</span>([a-z ()]+?) \d+%", layer.legend_html) if n != "not seen yet"]
    catalogue = {m.noun_phrase for m in CATALOGUE}
    assert listed and all(name in names or name == "other classes (not in this world)" for name in listed)
    assert len(listed) == len(set(listed))  # "tower" once, however many tower models the head knows
    assert not {n for n in listed if n in catalogue} - set(names)
    assert "not seen yet" in layer.legend_html and tuple(layer.rgb[0, 0]) == UNSEEN_RGB
    other = [tuple(c) for c in layer.rgb[4:].reshape(-1, 3)]
    assert OTHER_RGB in other or "other classes" not in layer.legend_html
    seen_all = build_layers(np.ones((32, 32, 32), np.float16), *zeros, heads, world_names=names)["semantic"]
    assert "not seen yet" not in seen_all.legend_html
    # 9 and 12: no "stopped" without a STOP; a stopped episode names the step the timeline ends at
    e = _episode_with_steps()
    e.result = replace(e.result, stopped=False, goal_distance=17.9)
    text = result_markdown(e)
    assert "stopped **" not in text and "without a STOP" in text and "outside the region" in text
    e.status = "cancelled"
    for i in range(1, 40):
        e.steps.append(replace(e.steps[0], step=i))
    assert "cancelled at step 39" in result_markdown(e) and "40" not in result_markdown(e)
    # 16: the environment id is a whole number; "-5" and "abc" are refused, not read as 0
    assert parse_env_id(" 76 ") == 76
    for bad in ("-5", "abc", "", "7.5", str(2**31)):
        with pytest.raises(ValueError):
            parse_env_id(bad)
    # instruction help: this world's names as the word being typed, and the template filled in
    assert suggestions("go to the left side of the palm", world) == ("palm tree",)
    assert set(suggestions("", world)) == {lm.noun_phrase for lm in world.landmarks}
    assert compose_instruction("", world, name="cone") == "go to the left side of the cone"
    assert compose_instruction("go to the back side of the cone", world, side="front") == \
        "go to the front side of the cone"
    assert compose_instruction("go to the back side of the cone", world, name="tent") == \
        "go to the back side of the tent"
    # 1: labels that would meet on the slider do not both print (environment 70: "in region" at 76 of 83)
    assert marks_clash((76, "in region"), (83, "83"), 83) and not marks_clash((20, "in region"), (83, "83"), 83)
    # the Actions plot: the cursor is a vertical line at the shown step, over the other series' values there
    e = _episode_with_steps()
    e.steps.extend(replace(e.steps[0], step=i, v=0.1 * i) for i in range(1, 30))
    x, v, omega, stop, line_05, band, cursor = actions_data(e, 20)
    k = int(np.nanargmax(cursor))
    assert x[k] == 20 and cursor[k - 1] == cursor[k + 1] == 0 and np.isnan(cursor).sum() == len(x) - 3
    assert v[k - 1] == v[k] == v[k + 1] and (line_05 == 0.5).all() and len({len(c) for c in (x, v, band)}) == 1


def test_the_first_view_shows_every_start_corner_and_the_drone():
    """Item 4 of issue 51: from the first camera, the whole field (every start corner, where the drone begins, with
    its frustum up to 3 m) lies inside a canvas 0.64 as wide as it is high (1280 x 800 between the side panels)."""
    from app.page.scene import LABEL_PX

    half_height = LABEL_PX["viewport"] / 2
    for x in (-1.0, 31.0):
        for y in (-1.0, 31.0):
            for z in (0.0, 3.0):
                left, top, right, bottom = label_box((x, y, z), "")  # a zero-width label: the point itself
                u, v = (left + right) / 2, bottom
                assert abs(u) < 0.64 * half_height and abs(v) < half_height, (x, y, z, u, v)


def test_the_ground_surfaces_are_farther_apart_than_the_depth_buffer_resolves():
    """Item 3 of issue 51: seen from near top-down, two of the ground's stacked surfaces fought for depth. With the
    view's near plane at CAMERA_NEAR, a 24-bit depth buffer resolves z^2 / (near 2^24) at distance z: far below
    the closest pair of surfaces (the field's top at -1 mm and the grid at +2 mm) from 60 m, where viser's own near
    plane (0.01 m) resolved 21 mm."""
    from app.page.scene import (
        CAMERA_FAR,
        CAMERA_NEAR,
        LAYER_HEIGHTS,
        OTHER_LAYER_HEIGHT,
        SIDES_HEIGHT,
        WHATIF_QUADRANT_HEIGHT,
    )

    heights = sorted([-0.001, 0.002, 0.005, 0.012, 0.016, WHATIF_QUADRANT_HEIGHT, *LAYER_HEIGHTS.values(),
                      OTHER_LAYER_HEIGHT, SIDES_HEIGHT])  # field top, grid, lakes, region, quadrant, what-if, layers
    gap = min(b - a for a, b in zip(heights, heights[1:], strict=False))

    def resolution(near: float, z: float = 60.0) -> float:
        return z * z / (near * 2**24)

    assert resolution(CAMERA_NEAR) < gap / 4 < resolution(0.01) and CAMERA_FAR > 100  # the field fits well inside


def test_principal_components_colour_like_features_alike_and_keep_their_colours():
    """Without a perception head the semantic map is drawn by its features' principal components: cells holding
    the same landmark's features share a colour, two landmarks differ, and a step that adds a little to the map
    (or shifts it) keeps the colours."""
    from app.render.colors import channels_rgb, principal_components

    rng = np.random.default_rng(0)
    a, b = rng.normal(size=32), rng.normal(size=32)
    semantic = 0.05 * rng.normal(size=(32, 20, 20))
    semantic[:, 2:5, 2:5] += a[:, None, None]
    semantic[:, 12:16, 10:14] += b[:, None, None]
    seen = np.zeros((20, 20), bool)
    seen[:, :16] = True
    rgb, _ = channels_rgb(principal_components(semantic, seen), seen, shared=True)
    first, second, ground = rgb[3, 3].astype(int), rgb[13, 11].astype(int), rgb[8, 8].astype(int)
    assert np.abs(rgb[2:5, 2:5].astype(int) - first).max() < 40 and np.abs(rgb[12:16, 10:14] - second).max() < 40
    assert min(np.abs(first - second).sum(), np.abs(first - ground).sum(), np.abs(second - ground).sum()) > 100
    later = semantic + 0.01 * rng.normal(size=semantic.shape) + 0.3  # the next step: a little noise, a shift
    rgb_later, _ = channels_rgb(principal_components(later, seen), seen, shared=True)
    assert np.abs(rgb_later[seen].astype(int) - rgb[seen]).mean() < 10  # no component flipped its sign
