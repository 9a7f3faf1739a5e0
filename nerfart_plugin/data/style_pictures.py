"""Sample style pictures by one command: ``python -m nerfart_plugin.data.style_pictures [--dest DIR]``.

Four photographs that ship with scikit-image (a dependency; each free to use, see :data:`PICTURES`) and one
picture drawn here (``swirls``: painted-looking swirling strokes), written as PNGs for ``+style_image=``:

    python -m nerfart_plugin.data.style_pictures                 # -> data/styles/{hubble,stain,coffee,retina,swirls}.png
    python -m nerfart_plugin guidance=imagenet +style_image=data/styles/swirls.png
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Callable, Optional

import imageio.v3 as iio
import numpy as np

from nerfart_plugin.utils.io import atomic_path

log = logging.getLogger("nerfart_plugin")

DEFAULT_DEST = Path("data") / "styles"


def swirls(size: int = 512, seed: int = 0) -> np.ndarray:
    """[size,size,3] uint8: swirling strokes around three vortices, blues and yellows as in a night sky, a brush
    grain across the strokes (a picture of this project's own, free to use)."""
    from scipy.ndimage import gaussian_filter
    from skimage.color import hsv2rgb

    rng = np.random.default_rng(seed)
    y, x = (np.mgrid[0:size, 0:size] + 0.5) / size * 2.0 - 1.0
    grain = gaussian_filter(rng.normal(size=(size, size)), sigma=(size / 256, size / 64))
    grain /= grain.std()
    stroke, weight, glow = np.zeros_like(x), np.zeros_like(x), np.zeros_like(x)
    for cx, cy, turn in ((-0.4, -0.3, 1), (0.45, 0.2, -1), (-0.1, 0.65, 1)):
        r = np.hypot(x - cx, y - cy)
        w = np.exp(-3.0 * r)
        stroke += w * np.sin(5 * np.arctan2(y - cy, x - cx) + turn * 28.0 * r + 0.7 * grain)  # 5: continuous
        weight += w
        glow += np.exp(-(r / 0.12) ** 2)
    stroke = 0.5 + 0.5 * stroke / weight
    hue = 0.62 - 0.07 * stroke - 0.45 * np.clip(glow, 0, 1)  # blue strokes, yellow at the vortices' eyes
    hsv = np.stack([hue % 1.0, 0.5 + 0.45 * stroke, 0.3 + 0.55 * stroke + 0.15 * np.clip(glow, 0, 1)], -1)
    return (hsv2rgb(np.clip(hsv, 0, 1)) * 255).round().astype(np.uint8)


def _skimage(name: str) -> Callable[[], np.ndarray]:
    def load() -> np.ndarray:
        import skimage.data

        return getattr(skimage.data, name)()
    return load


#: name -> (how it is made, where it comes from and its terms)
PICTURES: dict[str, tuple[Callable[[], np.ndarray], str]] = {
    "hubble": (_skimage("hubble_deep_field"), "scikit-image's hubble_deep_field: NASA, public domain"),
    "stain": (_skimage("immunohistochemistry"), "scikit-image's immunohistochemistry: CMMI, no known copyright "
                                                "restrictions"),
    "coffee": (_skimage("coffee"), "scikit-image's coffee: Rachel Michetti, CC0"),
    "retina": (_skimage("retina"), "scikit-image's retina: Mikael Häggström, CC0"),
    "swirls": (swirls, "drawn by nerfart_plugin.data.style_pictures.swirls, free to use"),
}


def write_pictures(dest: Path = DEFAULT_DEST, names: Optional[list[str]] = None) -> dict[str, Path]:
    """Write the pictures ``names`` (default all) as ``dest/<name>.png``; returns name -> path."""
    dest.mkdir(parents=True, exist_ok=True)
    out = {}
    for name in names or list(PICTURES):
        make, origin = PICTURES[name]
        path = dest / f"{name}.png"
        with atomic_path(path) as tmp:
            iio.imwrite(tmp, make(), extension=".png")
        log.info("%s (%s)", path, origin)
        out[name] = path
    return out


def main(argv: Optional[list[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m nerfart_plugin.data.style_pictures", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dest", type=Path, default=DEFAULT_DEST, help="folder to write into (default data/styles)")
    p.add_argument("names", nargs="*", metavar="NAME", help=f"pictures to write (default all: {', '.join(PICTURES)})")
    args = p.parse_args(argv)
    unknown = [n for n in args.names if n not in PICTURES]
    if unknown:
        p.error(f"no picture {', '.join(unknown)}; one of {', '.join(PICTURES)}")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    write_pictures(args.dest, args.names or None)
    return 0


if __name__ == "__main__":
    sys.exit(main())
