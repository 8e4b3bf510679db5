"""The linear probe of scripts/probe_grounding.py: fitted as a Linear(C -> 2) head the attribution reads."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from gsmn.attribution import positive_probability

pytestmark = pytest.mark.unit

spec = importlib.util.spec_from_file_location("probe_grounding",
                                              Path(__file__).parents[1] / "scripts" / "probe_grounding.py")
probe = importlib.util.module_from_spec(spec)
spec.loader.exec_module(probe)


def test_probe_recovers_a_linear_rule_as_a_two_class_head():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2000, 3))
    y = 2.0 * x[:, 1] - x[:, 0] + 0.1 * rng.normal(size=2000) > 1.5  # rare positives, as named landmarks are
    weight, bias = probe.fit_logistic(x, y)
    assert weight.shape == (2, 3) and bias.shape == (2,)
    p = positive_probability(x.T.reshape(3, 40, 50), weight, bias).reshape(-1)  # the attribution's reading
    assert np.allclose(p, 1 / (1 + np.exp(-(x @ weight[1] + bias[1]))), atol=1e-5)
    balanced = 0.5 * ((p[y] > 0.5).mean() + (p[~y] <= 0.5).mean())
    assert balanced > 0.95
    assert weight[1, 1] > 0 > weight[1, 0] and abs(weight[1, 2]) < 0.5 * weight[1, 1]  # reads the right features


def test_probe_finds_nothing_in_noise():
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(2000, 3)), rng.random(2000) < 0.2
    weight, bias = probe.fit_logistic(x, y)
    p = positive_probability(x.T.reshape(3, 40, 50), weight, bias).reshape(-1)
    assert 0.4 < 0.5 * ((p[y] > 0.5).mean() + (p[~y] <= 0.5).mean()) < 0.6


def test_paired_counts_the_episodes_only_one_model_grounds(tmp_path):
    other = tmp_path / "other.json"
    other.write_text('{"checkpoint": "b", "verdicts": {"probe": {"1": true, "2": true, "3": false, "4": null, '
                     '"5": true}}}')
    mine = {1: True, 2: False, 3: True, 4: True, 5: None, 6: True}  # 4-6: not seen by one of the two, or absent
    line = probe.paired(mine, str(other), "a")
    assert "over 3 episodes" in line and "by a only 1, by b only 1" in line and "p 1" in line
