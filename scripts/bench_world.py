"""Benchmark the world: median time of a 5 Hz step (physics), of a render, of a reset, and loop steps/s.

    python scripts/bench_world.py [--envs 5] [--steps 50] [--repeats 3]

Prints one row per look (paper: MuJoCo's shadow passes, no MSAA; paper, baked: the same look with the static
world's shadows baked once per world, gsmn/world/shadows.py; tiny: no shadows, no MSAA). Each figure is the median over
all measured calls; the loop rate is the median over repeats of (steps / wall time) for step + render.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import statistics
import time

import gsmn  # noqa: F401  (sets MUJOCO_GL before mujoco loads)
from gsmn.config import preset
from gsmn.world.assets import load_catalogue
from gsmn.world.env import Action, Env
from gsmn.world.sim import Simulator
from gsmn.world.spec import split_env_ids, world_for_env

LOOKS = {"paper": ("paper", "mujoco"), "paper, baked": ("paper", "baked"), "tiny": ("tiny", "mujoco")}


def bench(look: str, envs: int, steps: int, repeats: int) -> dict[str, float]:
    preset_name, shadow_method = LOOKS[look]
    config = preset(preset_name)
    config = dataclasses.replace(config, camera=dataclasses.replace(config.camera, shadow_method=shadow_method))
    catalogue = load_catalogue()
    physics, render, reset, loop_rates = [], [], [], []
    for env_id in split_env_ids("test", envs):
        world = world_for_env(env_id, config.world)
        t = time.perf_counter()
        sim = Simulator(world, config, catalogue)
        sim.render()  # the first render creates the GL context: part of the reset cost
        reset.append(time.perf_counter() - t)
        for k in range(steps):
            t = time.perf_counter()
            sim.step(1.6, 0.8 if (k // 10) % 2 else -0.8)
            physics.append(time.perf_counter() - t)
            t = time.perf_counter()
            sim.render()
            render.append(time.perf_counter() - t)
        sim.close()
    with Env(config, catalogue) as env:
        for _ in range(repeats):
            env.reset(70)
            t = time.perf_counter()
            for k in range(steps):
                env.step(Action(1.6, 0.8 if (k // 10) % 2 else -0.8))
            loop_rates.append(steps / (time.perf_counter() - t))
    return {"physics_ms": 1e3 * statistics.median(physics), "render_ms": 1e3 * statistics.median(render),
            "reset_ms": 1e3 * statistics.median(reset), "loop_steps_per_s": statistics.median(loop_rates)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, default=5)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}")
    print(f"{'preset':12} {'physics step (ms)':>18} {'render (ms)':>12} {'reset (ms)':>11} {'loop (steps/s)':>15}")
    for name in LOOKS:
        r = bench(name, args.envs, args.steps, args.repeats)
        print(f"{name:12} {r['physics_ms']:18.2f} {r['render_ms']:12.2f} {r['reset_ms']:11.1f} "
              f"{r['loop_steps_per_s']:15.1f}")


if __name__ == "__main__":
    main()
