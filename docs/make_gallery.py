"""Make a gallery picture of the README from finished stylization runs: per run, one held-out view (the
judge's second view) as source | stylized | the stylized surface's normals, at the run's own resolution,
each tile labelled. The runs are real: the README gives the commands that made them.

    python docs/make_gallery.py --out docs/images/gallery.png --runs outputs/stylizations/<run> ...
    python docs/make_gallery.py --out docs/images/ablations.png --runs <run> ... --labels full no_global ...
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def gallery_rows(folders: Sequence[Path], labels: Optional[Sequence[str]] = None) -> list[np.ndarray]:
    """Per run, its three labelled tiles (uint8 HxWx3 each, the run's own frame size); the stylized tile is
    labelled with ``labels[i]`` when given, else with the run's prompt."""
    from nerfart_plugin.api import open_run
    from nerfart_plugin.utils.images import label_image, to_uint8

    if labels is not None and len(labels) != len(folders):
        raise ValueError(f"{len(labels)} labels for {len(folders)} runs: give one label per run")
    tiles: list[np.ndarray] = []
    for i, folder in enumerate(folders):
        run = open_run(folder, device="cpu")
        views = run.metrics.get("judge", {}).get("views") or [0]
        view = views[min(1, len(views) - 1)]
        sty = run.render(view, channels=("rgb", "normal"))
        source = run.source.render(view, resolution=run.resolution)["rgb"]
        tiles += [label_image(to_uint8(source), "source"), label_image(to_uint8(sty["rgb"]), labels[i] if labels else run.metrics["prompt"]),
                  label_image(to_uint8(sty["normal"]), "geometry")]
    return tiles


def make_gallery(folders: Sequence[Path], out: Path, labels: Optional[Sequence[str]] = None) -> Path:
    """Write the gallery of ``folders`` (one row per run, labelled as :func:`gallery_rows`) to ``out``."""
    from nerfart_plugin.utils.images import image_grid, save_image

    out.parent.mkdir(parents=True, exist_ok=True)
    return save_image(image_grid(gallery_rows(folders, labels), ncols=3), out)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", nargs="+", type=Path, required=True, help="finished stylization run folders")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "images" / "gallery.png")
    p.add_argument("--labels", nargs="+", default=None, help="one label per run for its stylized tile (default: "
                   "the run's prompt), e.g. the ablation each run is")
    args = p.parse_args(argv)
    missing = [str(r) for r in args.runs if not (r / "final.ckpt").is_file()]
    if missing:
        p.error(f"not finished stylization runs (no final.ckpt): {', '.join(missing)}")
    if args.labels is not None and len(args.labels) != len(args.runs):
        p.error(f"--labels: {len(args.labels)} labels for {len(args.runs)} runs; give one per run")
    print(make_gallery(args.runs, args.out, args.labels))
    return 0


if __name__ == "__main__":
    sys.exit(main())
