"""Contact sheet of the first camera image of several worlds, each beside its top-down view.

    python scripts/contact_sheet.py [--env-ids 70,71,...] [--out docs/first_images.png]
"""

from __future__ import annotations

import argparse

from PIL import Image, ImageDraw

import gsmn  # noqa: F401  (sets MUJOCO_GL before mujoco loads)
from gsmn.config import preset
from gsmn.world.assets import load_catalogue
from gsmn.world.sim import Simulator
from gsmn.world.spec import split_env_ids, world_for_env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env-ids", default=None, help="comma-separated ids (default: first 12 test ids)")
    parser.add_argument("--out", default="docs/first_images.png")
    parser.add_argument("--cols", type=int, default=3)
    args = parser.parse_args()
    ids = [int(s) for s in args.env_ids.split(",")] if args.env_ids else split_env_ids("test", 12)
    config, catalogue = preset("paper"), load_catalogue()
    w, h, top, label = config.camera.width, config.camera.height, config.camera.height, 16
    tile_w, tile_h = w + top + 6, h + label
    rows = (len(ids) + args.cols - 1) // args.cols
    sheet = Image.new("RGB", (args.cols * tile_w + 6, rows * tile_h + 6), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for k, env_id in enumerate(ids):
        world = world_for_env(env_id, config.world)
        sim = Simulator(world, config, catalogue)
        fpv, topdown = Image.fromarray(sim.render()), Image.fromarray(sim.render_topdown(top))
        sim.close()
        x, y = 6 + (k % args.cols) * tile_w, 6 + (k // args.cols) * tile_h
        sheet.paste(fpv, (x, y + label))
        sheet.paste(topdown, (x + w + 2, y + label))
        draw.text((x, y + 2), f"env {env_id} ({world.split}): {len(world.landmarks)} landmarks", fill=(0, 0, 0))
    sheet.save(args.out)
    print(f"wrote {args.out} ({len(ids)} worlds)")


if __name__ == "__main__":
    main()
