"""Model speed on this machine: inference per step at batch 1 and training throughput (docs/model.md).

Inference: `ModelPolicy.act` itself, from a camera observation (uint8 image, numpy poses) to the action
(perceive + ground + controller for GSMN; features, filters and perceptron for the baselines), in float32 and
with the opt-in bfloat16 ResNet (`model.inference_bf16`). Training: forward +
backward + Adam step on a batch of B sequences of T steps (frames = B*T), with every objective. Medians of
several timed runs after warm-up. Inputs are random images with plausible camera poses: speed does not depend
on the pixels.

    python scripts/bench_model.py [--threads 2] [--batch 16] [--steps 8] [--repeats 7] [--kinds gsmn gs-fpv ...]
                                  [--device cuda]    # training on a GPU (inference stays on the CPU, as it runs)

By default the process keeps freed memory in its heap (gsmn.model.runtime.keep_freed_memory), as a training
process should; --plain-malloc measures without.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import time
from types import SimpleNamespace

import numpy as np
import torch

from gsmn.config import LossConfig, preset
from gsmn.model import Vocabulary, build_model, compute_losses, forward_batch
from gsmn.model.batch import Batch
from gsmn.model.policy import ModelPolicy
from gsmn.model.runtime import keep_freed_memory
from gsmn.world.env import Observation, Pose

INSTRUCTION = "go to the left side of the red barrel"


def camera_pose(x: float, y: float, yaw: float, altitude: float = 5.0, pitch_deg: float = 27.0) -> np.ndarray:
    """T_world_camera of a level drone at (x, y, yaw) with the camera pitched down (x right, y down, z forward)."""
    p = math.radians(pitch_deg)
    forward = np.array([math.cos(yaw) * math.cos(p), math.sin(yaw) * math.cos(p), -math.sin(p)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(forward, right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, forward], axis=1)
    T[:3, 3] = (x, y, altitude)
    return T


def random_batch(B: int, T: int, vocabulary: Vocabulary, rng: np.random.Generator) -> Batch:
    poses = np.stack([np.stack([rng.uniform(0, 30, T), rng.uniform(0, 30, T), rng.uniform(-3, 3, T)], -1)
                      for _ in range(B)]).astype(np.float32)  # (B, T, 3)
    T_world_camera = np.array([[camera_pose(*p) for p in seq] for seq in poses], dtype=np.float32)
    ids = vocabulary.encode(INSTRUCTION)
    M = 8
    return Batch(
        images=torch.from_numpy(rng.integers(0, 256, (B, T, 144, 256, 3), dtype=np.uint8)),
        T_world_camera=torch.from_numpy(T_world_camera),
        K=torch.tensor([[128.0, 0, 128], [0, 128, 72], [0, 0, 1]]).expand(B, 3, 3).contiguous(),
        poses=torch.from_numpy(poses),
        actions=torch.from_numpy(np.stack([rng.uniform(0, 1, (B, T)), rng.uniform(-1, 1, (B, T)),
                                           rng.integers(0, 2, (B, T))], -1).astype(np.float32)),
        mask=torch.ones(B, T, dtype=torch.bool),
        tokens=torch.tensor([ids] * B), lengths=torch.full((B,), len(ids)),
        landmark_xy=torch.from_numpy(rng.uniform(3, 27, (B, M, 2)).astype(np.float32)),
        landmark_class=torch.from_numpy(rng.integers(0, 63, (B, M))),
        landmark_valid=torch.ones(B, M, dtype=torch.bool),
        named_landmark=torch.zeros(B, dtype=torch.int64), side=torch.zeros(B, dtype=torch.int64),
        goal_xy=torch.from_numpy(rng.uniform(3, 27, (B, 2)).astype(np.float32)))


def median_time(fn, repeats: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def bench_inference(kind: str, config, vocabulary: Vocabulary, repeats: int) -> float:
    """Seconds per `ModelPolicy.act` at batch 1 (median over `repeats` 20-step episodes' mean step time): the
    policy's own call from a camera observation (numpy) to the action, as evaluation and the dashboard make it."""
    model = build_model(kind, config, vocabulary).eval()
    batch = random_batch(1, 20, vocabulary, np.random.default_rng(0))
    policy = ModelPolicy(model, vocabulary, config)
    task = SimpleNamespace(world=SimpleNamespace(env_id=0), instruction=SimpleNamespace(text=INSTRUCTION))
    observations = [Observation(image=batch.images[0, t].numpy(), T_world_camera=batch.T_world_camera[0, t].numpy(),
                                K=batch.K[0].numpy(), step=t, time=0.2 * t,
                                pose=Pose(position=np.array([*batch.poses[0, t, :2].tolist(), 5.0]),
                                          yaw=float(batch.poses[0, t, 2]), R_world_body=np.eye(3)))
                    for t in range(batch.steps)]

    def episode():
        policy.reset(task)
        for obs in observations:
            policy.act(obs)

    return median_time(episode, repeats) / batch.steps


def bench_training(kind: str, config, vocabulary: Vocabulary, B: int, T: int, repeats: int,
                   device: str = "cpu") -> float:
    """Training frames (B*T) per second."""
    model = build_model(kind, config, vocabulary).to(device).train()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3, weight_decay=1e-7)
    batch = random_batch(B, T, vocabulary, np.random.default_rng(0)).to(device)
    generator = torch.Generator(device=device).manual_seed(0)

    def step():
        optimizer.zero_grad(set_to_none=True)
        outputs = forward_batch(model, batch, generator)
        compute_losses(model, batch, outputs, LossConfig(), generator=generator).total.backward()
        optimizer.step()
        if device != "cpu":
            torch.cuda.synchronize(device)

    return B * T / median_time(step, repeats, warmup=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    parser.add_argument("--batch", type=int, default=16, help="training sequences per batch")
    parser.add_argument("--steps", type=int, default=8, help="training steps (T) per sequence")
    parser.add_argument("--repeats", type=int, default=7, help="timed runs; the median is reported")
    parser.add_argument("--kinds", nargs="+", default=["gsmn", "gs-fpv", "gs-fpv-mem"])
    parser.add_argument("--no-channels-last", action="store_true", help="run the ResNet in NCHW")
    parser.add_argument("--plain-malloc", action="store_true", help="leave glibc malloc's defaults")
    parser.add_argument("--device", default="cpu", help="where training is timed: cpu, cuda or cuda:N")
    args = parser.parse_args()
    tuned = False if args.plain_malloc else keep_freed_memory()
    torch.set_num_threads(args.threads)
    config = preset("paper")
    if args.no_channels_last:
        config = dataclasses.replace(config, model=dataclasses.replace(config.model, channels_last=False))
    vocabulary = Vocabulary.default()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, channels_last={config.model.channels_last}, "
          f"keep_freed_memory={tuned}, training on {args.device}"
          + (f" ({torch.cuda.get_device_name(args.device)})" if args.device != "cpu" else ""))
    bf16 = dataclasses.replace(config, model=dataclasses.replace(config.model, inference_bf16=True))
    print(f"{'kind':<12} {'inference ms/step (B=1)':>24} {'same, bf16 ResNet':>18} "
          f"{f'training frames/s (B={args.batch}, T={args.steps})':>34}")
    for kind in args.kinds:
        inference = bench_inference(kind, config, vocabulary, args.repeats)
        inference_bf16 = bench_inference(kind, bf16, vocabulary, args.repeats)
        training = bench_training(kind, config, vocabulary, args.batch, args.steps, args.repeats, args.device)
        print(f"{kind:<12} {inference * 1000:>24.2f} {inference_bf16 * 1000:>18.2f} {training:>34.1f}", flush=True)


if __name__ == "__main__":
    main()
