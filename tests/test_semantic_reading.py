"""The semantic map read as "which of this world's landmarks, or nothing" (issue 77, item 15), the legend of the 3D
view's colours and presenter mode's framing of the field (item 14), on hand-made heads and maps: no simulator, no
server, no browser.

The perception head here is the identity on 63 channels, so a cell's features are its class logits: a cell can be
made to read any class with any confidence."""

from __future__ import annotations

import re

import numpy as np
import pytest

from app.live.models import MapHeads
from app.live.recording import FINISHED, Episode, StepMaps, StepRecord, jpeg_bytes
from app.render import colors
from app.render.colors import (
    OTHER_RGB,
    PATHS_LEGEND,
    UNSEEN_RGB,
    name_palette,
    paths_legend_html,
    semantic_classes,
    world_reading,
)
from app.render.export import export_html, frame_image, semantic_key, step_layers
from app.render.layers import NOTHING_ALPHA, build_layers
from gsmn.config import preset
from gsmn.task.instructions import make_instruction
from gsmn.task.rollout import Task
from gsmn.world.landmarks import CATALOGUE
from gsmn.world.spec import world_for_env

pytestmark = pytest.mark.unit

NAMES = tuple(m.noun_phrase for m in CATALOGUE)
K = len(NAMES)
WORLD = world_for_env(245, preset("tiny").world)  # satellite dish, water tower, mushroom, palm tree, cone, ...
WORLD_NAMES = tuple(lm.noun_phrase for lm in WORLD.landmarks)
ORDER = sorted(set(WORLD_NAMES))


def heads() -> MapHeads:
    """The identity as the perception head: features are logits."""
    return MapHeads(np.eye(K, dtype=np.float32), np.zeros(K, np.float32),
                    np.array([[0, 0, 0], [1, 0, 0]], np.float32), np.zeros(2, np.float32),
                    np.array([[0, 0], [1, 0]], np.float32), np.zeros(2, np.float32), class_names=NAMES)


def logits(**by_class: float) -> np.ndarray:
    """A cell's features: -5 for every class but those given (catalogue model names, e.g. cone_1=4.0)."""
    cell = np.full(K, -5.0, np.float32)
    for model, value in by_class.items():
        cell[[m.name for m in CATALOGUE].index(model)] = value
    return cell


def semantic_map(n: int = 8) -> np.ndarray:
    """An n x n map, row 0 holding the cells A-D below, the rest never seen (exactly zero):
    A: sure of the gorilla (in this world); B: sure of a tank (not in it);
    C: the gorilla is the likeliest single class, but ten absent classes together are far likelier;
    D: two cone models (one name here) each below a tank, together above it and all else."""
    assert "gorilla" in WORLD_NAMES and "cone" in WORLD_NAMES and "tank" not in WORLD_NAMES
    absent = {m.name: 2.5 for m in CATALOGUE if m.noun_phrase not in WORLD_NAMES}
    c = {name: value for name, value in list(absent.items())[:10]}
    m = np.zeros((K, n, n), np.float32)
    m[:, 0, 0] = logits(gorilla=6.0)
    m[:, 0, 1] = logits(tank=6.0)
    m[:, 0, 2] = logits(gorilla=3.0, **c)
    m[:, 0, 3] = logits(cone_1=4.0, cone_2=4.0, tank=4.5)
    return m


def test_a_cell_reads_as_one_of_this_worlds_landmarks_or_nothing():
    h = heads()
    index, p, observed = world_reading(semantic_map(), h.perception_w, h.perception_b, NAMES, WORLD_NAMES)
    read = [ORDER[k] if k >= 0 else "nothing" for k in index[0, :4]]
    assert read == ["gorilla", "nothing", "nothing", "cone"]
    assert observed[0, :4].all() and not observed[1:].any()
    assert p[0, 0] > 0.9 and p[0, 1] > 0.9  # sure of the gorilla; sure that none of this world's is there
    assert p[0, 3] > 0.5  # the two cone models summed
    # over all 63 classes C reads the gorilla and D the tank: the mosaic the world reading leaves out
    classes = semantic_classes(semantic_map(), h.perception_w, h.perception_b)[0]
    assert NAMES[classes[0, 2]] == "gorilla" and NAMES[classes[0, 3]] == "tank"


def test_the_world_reading_draws_and_lists_only_this_worlds_landmarks_and_nothing():
    zeros = (np.zeros((3, 8, 8), np.float32), np.zeros((2, 8, 8), np.float32), np.zeros((2, 16, 16), np.float32))
    layer = build_layers(semantic_map(), *zeros, heads(), world_names=WORLD_NAMES,
                         semantic_reading="world")["semantic"]
    palette = name_palette(NAMES, WORLD_NAMES)
    gorilla = palette[ORDER.index("gorilla")].astype(float)
    assert np.allclose(layer.rgb[0, 0] / gorilla, layer.rgb[0, 0][0] / gorilla[0], atol=0.02)  # gorilla's hue
    assert tuple(layer.rgb[0, 1]) == OTHER_RGB and tuple(layer.rgb[0, 2]) == OTHER_RGB  # nothing: one pale colour
    assert tuple(layer.rgb[5, 5]) == UNSEEN_RGB
    assert layer.alpha[0, 0] == 1.0 and layer.alpha[0, 1] == pytest.approx(NOTHING_ALPHA) and layer.alpha[5, 5] == 0
    assert "this world's landmarks" in layer.title
    # every landmark of the world in the legend, in name order, shown or not, then nothing and the unseen grey
    listed = re.findall(r"</span>([a-z ()]+?) \d+%", layer.legend_html)
    assert listed == [*ORDER, "nothing (none of these)", "not seen yet"]
    assert "other classes" not in layer.legend_html
    # over all classes the same map keeps its mosaic: C is the gorilla's colour there
    every = build_layers(semantic_map(), *zeros, heads(), world_names=WORLD_NAMES)["semantic"]
    assert tuple(every.rgb[0, 2]) != OTHER_RGB and "other classes" in every.legend_html
    with pytest.raises(ValueError, match="semantic_reading"):
        build_layers(semantic_map(), *zeros, heads(), semantic_reading="mine")


def episode() -> Episode:
    """One step in world 245 whose maps are `semantic_map()` (32 x 32) and empty relevance and goal maps."""
    instruction = make_instruction(WORLD, 0, "left")
    e = Episode(id=3, task=Task(WORLD, instruction, np.zeros((2, 2))), policy="model", system="gsmn",
                checkpoint="ckpt", horizon=20, status=FINISHED)
    maps = StepMaps({"semantic_map_w": semantic_map(32).astype(np.float16),
                     "relevance_map_w": np.zeros((3, 32, 32), np.float16),
                     "goal_map_w": np.zeros((2, 32, 32), np.float16),
                     "goal_map_r": np.zeros((2, 64, 64), np.float16)}, np.zeros(3, np.float32), 1.0, 0.0, 0.1)
    e.steps.append(StepRecord(0, 0.0, (WORLD.start_x, WORLD.start_y, 2.0), 0.0, np.eye(4, dtype=np.float32),
                              jpeg_bytes(np.zeros((144, 256, 3), np.uint8)), 1.0, 0.0, False, maps))
    return e


def test_exports_read_the_map_as_this_worlds_landmarks_with_their_legend():
    e, h = episode(), heads()
    shown = step_layers(e, 0, h)["semantic"]  # the exports' and the presenter card's reading
    assert tuple(shown[0, 2]) == OTHER_RGB and tuple(step_layers(e, 0, h, semantic_reading="all")["semantic"][0, 2]) \
        != OTHER_RGB
    key = semantic_key(e, h)
    assert [label for label, _ in key] == [*ORDER, "nothing", "not seen yet"]
    # the GIF's frame writes that legend under the caption: each colour's swatch is in its bottom strip
    frame = frame_image(e, 0, h)
    strip = {tuple(c) for c in frame[-24:].reshape(-1, 3)}
    assert all(rgb in strip for _, rgb in key[:5]) and OTHER_RGB in strip
    # the HTML page carries each step's legend, shown under the semantic map
    page = export_html(e, h)
    assert "nothing (none of these)" in page and all(name in page for name in ORDER)
    assert 'key.id = "legend"' in page and "which of this world's landmarks, or nothing" in page


def test_the_paths_legend_names_the_3d_views_colours():
    from app.page import scene
    from app.page.presenter import card_html

    assert (scene.POLICY_RGB, scene.DEMO_RGB, scene.QUADRANT_RGB) == (colors.POLICY_RGB, colors.DEMO_RGB,
                                                                     colors.QUADRANT_RGB)
    legend = paths_legend_html()
    for rgb, label in PATHS_LEGEND:
        assert f"rgb({rgb[0]},{rgb[1]},{rgb[2]})" in legend and label in legend
    assert "blue line: the path the drone flew" in legend and "red line: the demonstration path" in legend
    card = card_html(episode(), 0, heads())
    assert "yellow ring: the drone" in card and "blue line" in card and "nothing (none of these)" in card


def test_presenter_mode_frames_the_field_for_a_wider_canvas():
    from app.page.scene import DEFAULT_CAMERA, framing_camera, in_view

    corners = [(x, y, 0.0) for x in (0.0, 30.0) for y in (0.0, 30.0)]
    target = np.asarray(DEFAULT_CAMERA["look_at"])
    first = np.linalg.norm(np.asarray(DEFAULT_CAMERA["position"]) - target)
    assert np.linalg.norm(np.asarray(framing_camera(0.64)["position"]) - target) == pytest.approx(first, rel=0.02)
    wide = framing_camera(810 / 800)  # presenter mode at 1280 x 800
    distance = np.linalg.norm(np.asarray(wide["position"]) - target)
    assert distance < 0.8 * first
    assert all(in_view(c, wide, 810 / 800) for c in corners)
    nearer = {**wide, "position": tuple(target + 0.9 * (np.asarray(wide["position"]) - target))}
    assert not all(in_view(c, nearer, 810 / 800, 0.9) for c in corners)
