"""Make the shipped default scene: a downscaled copy of an IDR/VolSDF scene folder.

    python -m nerfart_plugin.data.make_default_scene /work/shared/data/girl nerfart_plugin/assets/head --size 256

Writes ``DST/images/*.jpg`` (JPEG quality 92), ``DST/matte/*.png`` and
``DST/cameras.npz`` whose ``world_mat_i`` rows are rescaled so the projections
land on the resized pixels (``scale_mat_i`` copied unchanged), i.e. the same
format, loadable by the "h3ds" loader unchanged. Every file is written atomically.
"""

from __future__ import annotations

import argparse
import io
import logging
from pathlib import Path

import numpy as np
from PIL import Image

from nerfart_plugin.data.h3ds import CAMERA_FILES
from nerfart_plugin.data.images import find_mask_folder, list_images, match_masks, target_size
from nerfart_plugin.errors import DataError
from nerfart_plugin.utils.io import atomic_path

log = logging.getLogger(__name__)


def make_default_scene(src: Path, dst: Path, size: int = 256, quality: int = 92) -> list[Path]:
    """Downscale the scene at ``src`` so the long image side is ``size``; return written files."""
    src, dst = Path(src), Path(dst)
    cam_path = next((src / f for f in CAMERA_FILES if (src / f).is_file()), None)
    if cam_path is None:
        raise DataError(f"No cameras.npz in {src}: the source must be an IDR/VolSDF/NeuS scene folder.")
    notes: list[str] = []
    images = list_images(src / "images", notes)
    mask_dir = find_mask_folder(src)
    masks = match_masks(images, list_images(mask_dir, notes), notes) if mask_dir else []
    written: list[Path] = []
    with Image.open(images[0]) as im:
        w0, h0 = im.size
    w1, h1 = target_size(w0, h0, size)
    sx, sy = w1 / w0, h1 / h0
    for i, p in enumerate(images):
        with Image.open(p) as im:
            out = im.convert("RGB").resize((w1, h1), Image.Resampling.LANCZOS)
        target = dst / "images" / f"{i:04d}.jpg"
        with atomic_path(target) as tmp:
            out.save(tmp, format="JPEG", quality=quality)
        written.append(target)
    for i, p in enumerate(masks):
        with Image.open(p) as im:
            out = im.convert("L").resize((w1, h1), Image.Resampling.LANCZOS)
        target = dst / "matte" / f"{i:04d}.png"
        with atomic_path(target) as tmp:
            out.save(tmp, format="PNG", optimize=True)
        written.append(target)
    with np.load(cam_path, allow_pickle=False) as data:
        arrays = {k: np.asarray(data[k]) for k in data.files if k.startswith(("world_mat_", "scale_mat_"))}
    S = np.diag([sx, sy, 1.0, 1.0])
    for k in list(arrays):
        if k.startswith("world_mat_") and not k.startswith("world_mat_inv"):
            W = arrays[k].astype(np.float64)
            arrays[k] = (S[: W.shape[0], : W.shape[0]] @ W).astype(np.float32)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    with atomic_path(dst / "cameras.npz") as tmp:
        tmp.write_bytes(buf.getvalue())
    written.append(dst / "cameras.npz")
    log.info("wrote %d files to %s (%dx%d -> %dx%d)", len(written), dst, w0, h0, w1, h1)
    return written


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("src", type=Path, help="IDR/VolSDF scene folder (images/, matte/, cameras.npz)")
    ap.add_argument("dst", type=Path, help="output folder")
    ap.add_argument("--size", type=int, default=256, help="long image side in pixels")
    ap.add_argument("--quality", type=int, default=92, help="JPEG quality")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    make_default_scene(args.src, args.dst, args.size, args.quality)


if __name__ == "__main__":
    main()
