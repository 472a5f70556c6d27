#!/usr/bin/env python
"""Rebuild the synthetic-scene data shipped in torchface/data from the shared assets (development only).

Writes torchface/data/james/{james.npz, james_texture.jpg, LICENSE.txt} and torchface/data/photos/
{james_render.jpg, candide3_uv_<photo>.npz} (CANDIDE-3 texture mappings), and prints conversion figures.
Usage: python scripts/build_synth_data.py [--assets FOLDER]   (default: TORCHFACE_ASSETS, else ../shared/assets)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# _argtypes first (run as a command, it makes a Ctrl-C during the heavy imports below one line, status 130)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # _argtypes beside this script, however it is run
from _argtypes import assets_folder  # noqa: E402
from _argtypes import run_command  # noqa: E402

from torchface.synth.james import build_james_data
from torchface.synth.subjects import build_candide_textures

ROOT = Path(__file__).resolve().parents[1]
#: What torchface.synth.james.build_james_data reads from the assets' james folder.
JAMES_FILES = ("james.obj", "james.jpg", "james.ljson", "LICENSE.txt")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--assets", type=Path, default=assets_folder(),
                        help="the shared assets folder (default: TORCHFACE_ASSETS, else ../shared/assets beside the "
                        "repository)")
    args = parser.parse_args(argv)
    james_dir = args.assets / "james"
    if not james_dir.is_dir():
        raise SystemExit(f"build_synth_data.py: error: no James assets at {james_dir} (--assets, or TORCHFACE_ASSETS)")
    missing = [name for name in JAMES_FILES if not (james_dir / name).is_file()]
    if missing:  # (a traceback from trimesh or numpy before, once the package data had begun to change)
        raise SystemExit(f"build_synth_data.py: error: {james_dir} lacks {', '.join(missing)}")
    out = ROOT / "torchface" / "data" / "james"
    figures = build_james_data(james_dir, out)
    print(f"wrote {out}: " + ", ".join(f"{k}={v:.2f}" for k, v in figures.items()))
    photos = ROOT / "torchface" / "data" / "photos"
    figures = build_candide_textures(photos)
    print(f"wrote {photos}: " + ", ".join(f"{k}={v:.2f}" for k, v in figures.items()))


if __name__ == "__main__":
    run_command(main)
