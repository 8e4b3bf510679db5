"""A fixed-seed forward pass of a tiny GSMN on fixed inputs against saved reference tensors
(tests/golden/gsmn_tiny.safetensors, written by tests/golden/make_gsmn_tiny.py): a change that alters the model's
computation, meant or not, shows here first. Regenerate the reference only for a change meant to alter it."""

from __future__ import annotations

import runpy
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

pytestmark = pytest.mark.unit

GOLDEN = Path(__file__).resolve().parent / "golden"
golden_outputs = runpy.run_path(str(GOLDEN / "make_gsmn_tiny.py"))["golden_outputs"]  # the reference's own recipe


def test_a_tiny_gsmn_computes_what_it_computed_when_the_reference_was_saved():
    reference = load_file(GOLDEN / "gsmn_tiny.safetensors")
    now = golden_outputs()
    assert set(now) == set(reference)
    for name, expected in reference.items():
        torch.testing.assert_close(now[name], expected, rtol=1e-4, atol=1e-5, msg=lambda m, n=name: f"{n}: {m}")
