"""Writes tests/golden/gsmn_tiny.safetensors: a fixed-seed forward pass of a tiny GSMN on fixed inputs, the reference
tests/test_golden.py compares the model with. Run it only when a change of the model's computation is meant (and
say so in the commit):

    python tests/golden/make_gsmn_tiny.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from safetensors.torch import save_file

HERE = Path(__file__).resolve().parent


def golden_inputs() -> dict[str, torch.Tensor]:
    """Fixed inputs: 2 episodes of 3 steps, tiny camera, poses and instruction tokens from a seeded generator."""
    from gsmn.config import preset

    c = preset("tiny")
    g = torch.Generator().manual_seed(1234)
    B, T, H, W = 2, 3, c.camera.height, c.camera.width
    images = torch.randint(0, 256, (B, T, H, W, 3), generator=g, dtype=torch.uint8)
    T_wc = torch.eye(4).repeat(B, T, 1, 1)
    T_wc[..., :3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # looking along +x
    T_wc[..., 0, 3] = torch.linspace(2.0, 6.0, T)
    T_wc[..., 1, 3] = 8.0
    T_wc[..., 2, 3] = 3.0
    K = torch.tensor([[W / 2, 0.0, W / 2], [0.0, W / 2, H / 2], [0.0, 0.0, 1.0]])
    poses = torch.stack([T_wc[..., 0, 3], T_wc[..., 1, 3], torch.zeros(B, T)], dim=-1)
    tokens = torch.randint(2, 20, (B, 9), generator=g)
    return {"images": images, "T_world_camera": T_wc, "K": K, "poses": poses, "tokens": tokens,
            "lengths": torch.tensor([9, 6])}


def golden_outputs() -> dict[str, torch.Tensor]:
    from gsmn.config import preset
    from gsmn.model import build_model

    torch.manual_seed(0)
    model = build_model("gsmn", preset("tiny")).eval()
    x = golden_inputs()
    with torch.inference_mode():
        out = model(x["images"], x["T_world_camera"], x["K"], x["poses"], x["tokens"], x["lengths"])
    return {name: getattr(out, name).contiguous() for name in
            ("sentence_embedding", "relevance_map_w", "goal_map_w", "v", "omega", "stop_logit")} | {
        "semantic_map_w_sum": out.semantic_map_w.sum(dim=(2, 3, 4)).contiguous()}


if __name__ == "__main__":
    sys.path.insert(0, str(HERE.parents[1]))
    save_file(golden_outputs(), str(HERE / "gsmn_tiny.safetensors"))
    print(f"wrote {HERE / 'gsmn_tiny.safetensors'}")
