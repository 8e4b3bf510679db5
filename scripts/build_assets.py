"""Write the landmark meshes and catalogue: ``python scripts/build_assets.py [--out assets]``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gsmn.world.assets import ASSETS_DIR, load_catalogue, write_assets  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=ASSETS_DIR, help=f"assets directory (default {ASSETS_DIR})")
    args = parser.parse_args()
    write_assets(args.out)
    models = load_catalogue(args.out)
    files = sorted((args.out / "landmarks").rglob("*"))
    size = sum(f.stat().st_size for f in files if f.is_file())
    triangles = sum(len(p.faces) for m in models for p in m.parts)
    print(f"wrote {len(models)} landmark models ({triangles} triangles, {size / 1e6:.2f} MB) "
          f"to {args.out / 'landmarks'}")


if __name__ == "__main__":
    main()
