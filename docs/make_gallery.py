"""Make a gallery picture of the README from finished stylization runs: per run, one held-out view (the
judge's second view) as source | stylized | the stylized surface's normals, at the run's own resolution,
each tile labelled. The runs are real: the README gives the commands that made them.

    python docs/make_gallery.py --out docs/images/gallery.png --runs outputs/stylizations/<run> ...
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def gallery_rows(folders: Sequence[Path]) -> list[np.ndarray]:
    """Per run, its three labelled tiles (uint8 HxWx3 each, the run's own frame size)."""
    from nerfart_plugin.api import open_run
    from nerfart_plugin.export.video import label_image, to_uint8

    tiles: list[np.ndarray] = []
    for folder in folders:
        run = open_run(folder, device="cpu")
        views = run.metrics.get("judge", {}).get("views") or [0]
        view = views[min(1, len(views) - 1)]
        sty = run.render(view, channels=("rgb", "normal"))
        source = run.source.render(view, resolution=run.resolution)["rgb"]
        tiles += [label_image(to_uint8(source), "source"), label_image(to_uint8(sty["rgb"]), run.metrics["prompt"]),
                  label_image(to_uint8(sty["normal"]), "geometry")]
    return tiles


def make_gallery(folders: Sequence[Path], out: Path) -> Path:
    """Write the gallery of ``folders`` (one row per run) to ``out``."""
    from nerfart_plugin.export.video import image_grid, save_image

    out.parent.mkdir(parents=True, exist_ok=True)
    return save_image(image_grid(gallery_rows(folders), ncols=3), out)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", nargs="+", type=Path, required=True, help="finished stylization run folders")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "images" / "gallery.png")
    args = p.parse_args(argv)
    missing = [str(r) for r in args.runs if not (r / "final.ckpt").is_file()]
    if missing:
        p.error(f"not finished stylization runs (no final.ckpt): {', '.join(missing)}")
    print(make_gallery(args.runs, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
