"""Shared test set-up: headless rendering must be chosen before any test module imports mujoco; the tiers (which
tests `pytest -m fast` runs); the fixtures many modules share: one untrained checkpoint per run, `gsmn serve`
processes, and the training tests' expert stores."""

import json
import os
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")
if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    # Several workers share the cores: one torch thread in each process they start (gsmn.model.runtime; set before
    # any test module imports torch), or their threads spin against each other.
    os.environ.setdefault("GSMN_MAX_THREADS", "1")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("LP_NUM_THREADS", "1")  # Mesa's software renderer: one rasterizer thread, not one a core

# The tiers (README.md, "Tests"). Every test module names its tier in a module-level `pytestmark`
# (tests/test_structure.py checks it): `unit` for unit, contract and golden tests, or what makes it heavy.
# A test of a `unit` module that is heavy carries that marker itself.
HEAVY = ("server", "browser", "training", "cluster", "slow")  # registered in pyproject.toml
# fixtures that start what a fast test may not: a `gsmn serve` process
HEAVY_FIXTURES = {"gsmn_serve": "server"}


# The modules run longest first, so that xdist's workers start the long modules early and finish on the many short
# ones, instead of one long module running last while the other worker idles: their seconds in the last full run
# (tests/durations.json, written by scripts/test_durations.py), a module not in it by the rough cost of its tests'
# heaviest markers (seconds on two cores).
DURATIONS = Path(__file__).with_name("durations.json")
COST = {"training": 30.0, "cluster": 20.0, "browser": 20.0, "server": 8.0, "slow": 8.0}
FAST_COST = 0.2


def pytest_configure(config):
    """Keep the order given below under `--dist loadfile`: xdist would otherwise reorder the files by their number of
    tests, which sends the files of one or two long tests (the browser walk-throughs) last."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def cost(item) -> float:
    return max((COST[name] for name in COST if item.get_closest_marker(name)), default=FAST_COST)


def module_seconds(items) -> dict[str, float]:
    estimate: dict[str, float] = {}
    for item in items:
        module = item.nodeid.split("::")[0]
        estimate[module] = estimate.get(module, 0.0) + cost(item)
    try:
        measured = json.loads(DURATIONS.read_text())
    except (OSError, ValueError):
        measured = {}
    return {module: float(measured.get(module, seconds)) for module, seconds in estimate.items()}


@pytest.hookimpl(tryfirst=True)  # before `-m` selects
def pytest_collection_modifyitems(config, items):
    """Mark `fast` every test that carries none of the heavy markers, and run the modules longest first
    (module_seconds; the tests of a module stay together and in their order)."""
    for item in items:
        if not any(item.get_closest_marker(name) for name in HEAVY):
            item.add_marker(pytest.mark.fast)
    seconds = module_seconds(items)
    items.sort(key=lambda item: -seconds[item.nodeid.split("::")[0]])  # stable: a module's order kept


@pytest.hookimpl(tryfirst=True)  # before its fixtures are set up
def pytest_runtest_setup(item):
    """A fast test that would start a server through a fixture fails instead."""
    if item.get_closest_marker("fast"):
        needs = [f"{name} ({marker})" for name, marker in HEAVY_FIXTURES.items() if name in item.fixturenames]
        if needs:
            pytest.fail(f"a fast test may not use {', '.join(needs)}: mark it (or its module) with that marker",
                        pytrace=False)


@pytest.fixture(scope="session")
def untrained_checkpoint(tmp_path_factory):
    """The folder of an untrained tiny GSMN checkpoint (`make_untrained_checkpoint`'s defaults: seed 0, controller
    biased to fly), built once per run for every xdist worker (support.untrained_checkpoint). Read-only: a test that
    changes a checkpoint copies it first (`shutil.copytree(..., copy_function=shutil.copyfile)`); at the end of the
    session it is checked unchanged."""
    from support import tree_digest, untrained_checkpoint

    folder = untrained_checkpoint(tmp_path_factory)
    yield folder
    assert tree_digest(folder) == (folder.parent / "built").read_text(), \
        f"a test changed the shared untrained checkpoint {folder}: copy it instead"


@pytest.fixture(scope="module")
def gsmn_serve():
    """Start a `gsmn serve` process: `gsmn_serve(data_dir, checkpoint, *options, horizon=..., ...)` takes
    support.Serve's arguments and returns it started (`.client` on its API, `.page`, `.proc`, `.output()`,
    `.stop()`, `.kill()`, `.start()` again). Each is stopped when the test stops it, or when the module ends."""
    from support import Serve

    started: list[Serve] = []

    def start(*args, **kwargs) -> Serve:
        serve = Serve(*args, **kwargs)
        started.append(serve)
        return serve.start()

    yield start
    for serve in reversed(started):
        serve.stop()


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """Expert stores for the training tests: 4 train episodes (environments 0-3) and 2 dev (85, 86) of the tiny
    preset, each the first 20 steps of the expert's flight, so that those tests take seconds."""
    from gsmn.config import preset, with_overrides
    from gsmn.training.collect import collect_expert
    from gsmn.training.store import EpisodeStore

    config = with_overrides(preset("tiny"), {"task.horizon": "20"})
    root = tmp_path_factory.mktemp("data")
    train, dev = EpisodeStore(root / "train"), EpisodeStore(root / "dev")
    collect_expert(train, [0, 1, 2, 3], config, workers=2)
    collect_expert(dev, [85, 86], config)
    return train, dev
