"""The renderer's levers at the paper's look, measured side by side in one run: the median time of a forward-camera
render and how far its pixels are from the paper preset's (shadow map 1024, MuJoCo's default shadow clip).

    python scripts/bench_render_levers.py [--envs 3] [--steps 40]

Every setting renders the same frames: one simulator per setting, stepped with the same actions (the physics is
deterministic), the renders interleaved so that load on the machine falls on all of them alike. A setting is
(shadow map size, shadow clip, shadows on, shadow method: MuJoCo's passes or baked, gsmn/world/shadows.py); the
clip scales the part of the scene the directional light's shadow map covers (`visual/map shadowclip`), so a smaller
map with a tighter clip keeps the texels per metre. Pixel
figures: the share of pixels whose largest channel difference from the reference is over 16 levels, and the mean
absolute difference. Results: docs/experiments.md, "Rendering at the paper's look".
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import gsmn  # noqa: F401  (sets MUJOCO_GL before mujoco loads)
from gsmn.config import preset
from gsmn.world.assets import load_catalogue
from gsmn.world.sim import Simulator
from gsmn.world.spec import split_env_ids, world_for_env

SETTINGS = {  # name: (shadow map size, shadow clip or None for MuJoCo's default, shadows, shadow method)
    "paper (1024)": (1024, None, True, "mujoco"),
    "512": (512, None, True, "mujoco"),
    "256": (256, None, True, "mujoco"),
    "1024, clip 0.5": (1024, 0.5, True, "mujoco"),
    "512, clip 0.5": (512, 0.5, True, "mujoco"),
    "256, clip 0.25": (256, 0.25, True, "mujoco"),
    "no shadows": (1024, None, False, "mujoco"),
    "baked shadows": (1024, None, True, "baked"),
}


def simulator(world, config, catalogue, size: int, clip: float | None, shadows: bool, method: str) -> Simulator:
    import dataclasses

    config = dataclasses.replace(config, camera=dataclasses.replace(config.camera, shadow_size=size, shadows=shadows,
                                                                    shadow_method=method))
    sim = Simulator(world, config, catalogue)
    if clip is not None:
        sim.model.vis.map.shadowclip = clip
    return sim


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--envs", type=int, default=3)
    ap.add_argument("--steps", type=int, default=40)
    args = ap.parse_args()
    config, catalogue = preset("paper"), load_catalogue()
    times = {name: [] for name in SETTINGS}
    over, mean_abs = {name: [] for name in SETTINGS}, {name: [] for name in SETTINGS}
    clip0 = None
    for env_id in split_env_ids("test", args.envs):
        world = world_for_env(env_id, config.world)
        sims = {name: simulator(world, config, catalogue, *s) for name, s in SETTINGS.items()}
        clip0 = clip0 or sims["paper (1024)"].model.vis.map.shadowclip
        for sim in sims.values():
            sim.render()  # the GL context and shadow map made before timing
        for k in range(args.steps):
            frames = {}
            for name, sim in sims.items():
                sim.step(1.6, 0.8 if (k // 10) % 2 else -0.8)
                t = time.perf_counter()
                frames[name] = sim.render().astype(np.int16)
                times[name].append(time.perf_counter() - t)
            reference = frames["paper (1024)"]
            for name, frame in frames.items():
                d = np.abs(frame - reference).max(-1)
                over[name].append(float((d > 16).mean()))
                mean_abs[name].append(float(np.abs(frame - reference).mean()))
        for sim in sims.values():
            sim.close()
    base = statistics.median(times["paper (1024)"])
    print(f"{args.envs} test environments x {args.steps} steps; MuJoCo's default shadow clip {clip0:g}")
    print(f"{'setting':18} {'ms/render':>10} {'x paper':>8} {'pixels >16 levels':>18} {'mean |diff|':>12}")
    for name in SETTINGS:
        ms = 1000 * statistics.median(times[name])
        print(f"{name:18} {ms:10.1f} {ms / (1000 * base):8.2f} {100 * np.mean(over[name]):17.2f}% "
              f"{np.mean(mean_abs[name]):12.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
