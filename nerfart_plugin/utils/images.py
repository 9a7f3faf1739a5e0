"""Images as the project handles them: the one converter (:func:`to_uint8`), side-by-side and grid layouts with
labels, and atomic PNG / JPEG writes.

Images are HxWx3 (or HxW grey, or HxWx4 RGBA -> alpha dropped) arrays (numpy or torch), uint8 in [0,255] or
float in [0,1] (clipped).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from nerfart_plugin.errors import DataError
from nerfart_plugin.utils.io import atomic_path


def to_uint8(frame: np.ndarray, normalize: bool = False) -> np.ndarray:
    """The project's one image converter: HxW, HxWx1, HxWx3 or HxWx4 uint8/float image (numpy or torch)
    -> HxWx3 uint8 (floats taken in [0,1], rounded). ``normalize``: a one-channel float image (a depth
    map) is first scaled to its own min..max."""
    a = np.asarray(frame) if not hasattr(frame, "detach") else frame.detach().float().cpu().numpy()
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4):
        raise DataError(f"Expected an HxWx3 image, got shape {a.shape}; pass RGB frames (H, W, 3).")
    if a.shape[2] == 1:
        if normalize and np.issubdtype(a.dtype, np.floating):
            lo, hi = float(np.nanmin(a)), float(np.nanmax(a))
            a = (a - lo) / max(hi - lo, 1e-8)
        a = np.repeat(a, 3, axis=2)
    a = a[..., :3]
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a)
    if np.issubdtype(a.dtype, np.floating):
        a = np.nan_to_num(a.astype(np.float32), nan=0.0)
        return (np.clip(a, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return np.clip(a, 0, 255).astype(np.uint8)


def pad_to_even(frame: np.ndarray) -> np.ndarray:
    """Replicate-pad the last row/column so height and width are even."""
    h, w = frame.shape[:2]
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def label_image(img: np.ndarray, text: str) -> np.ndarray:
    """Draw ``text`` in the top-left corner of an HxWx3 uint8 image (PIL default font)."""

    im = Image.fromarray(img)
    draw = ImageDraw.Draw(im)
    size = max(10, img.shape[0] // 20)
    try:
        font = ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1
        font = ImageFont.load_default()
    x0, y0, x1, y1 = draw.textbbox((4, 4), text, font=font)
    draw.rectangle((x0 - 2, y0 - 2, x1 + 2, y1 + 2), fill=(0, 0, 0))
    draw.text((4, 4), text, fill=(255, 255, 255), font=font)
    return np.asarray(im)


def side_by_side(
    a: np.ndarray, b: np.ndarray, labels: tuple[str, str] | None = ("source", "stylized"), gap: int = 4
) -> np.ndarray:
    """[H, Wa+gap+Wb, 3] uint8: ``a`` left of ``b`` (white gap), optional text labels.

    Images of different heights are bottom-padded with white to the taller one.
    """
    a, b = to_uint8(a), to_uint8(b)
    if labels is not None:
        a, b = label_image(a, labels[0]), label_image(b, labels[1])
    h = max(a.shape[0], b.shape[0])
    pad = lambda x: np.pad(x, ((0, h - x.shape[0]), (0, 0), (0, 0)), constant_values=255)
    spacer = np.full((h, gap, 3), 255, np.uint8)
    return np.concatenate([pad(a), spacer, pad(b)], axis=1)


def image_grid(images: Sequence[np.ndarray], ncols: int | None = None, gap: int = 2) -> np.ndarray:
    """Tile images (any sizes; cells sized to the largest) into one uint8 HxWx3 grid."""
    if len(images) == 0:
        raise DataError("image_grid: no images given.")
    imgs = [to_uint8(i) for i in images]
    ncols = ncols or int(np.ceil(np.sqrt(len(imgs))))
    nrows = int(np.ceil(len(imgs) / ncols))
    ch, cw = max(i.shape[0] for i in imgs), max(i.shape[1] for i in imgs)
    grid = np.full((nrows * ch + (nrows - 1) * gap, ncols * cw + (ncols - 1) * gap, 3), 255, np.uint8)
    for n, im in enumerate(imgs):
        r, c = divmod(n, ncols)
        y, x = r * (ch + gap), c * (cw + gap)
        grid[y : y + im.shape[0], x : x + im.shape[1]] = im
    return grid


def with_caption(img: np.ndarray, text: str) -> np.ndarray:
    """``img`` (HxWx3) under a white band holding ``text`` in black, wrapped to the image's width."""
    import textwrap

    img = to_uint8(img)
    size = max(11, min(18, img.shape[1] // 40))
    try:
        font = ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1
        font = ImageFont.load_default()
    chars = max(20, int(img.shape[1] / (0.55 * size)))
    lines = textwrap.wrap(text, chars) or [""]
    band = Image.new("RGB", (img.shape[1], (len(lines) * (size + 4)) + 8), (255, 255, 255))
    draw = ImageDraw.Draw(band)
    for i, line in enumerate(lines):
        draw.text((4, 4 + i * (size + 4)), line, fill=(0, 0, 0), font=font)
    return np.concatenate([np.asarray(band), img], axis=0)


def save_image(image: np.ndarray, path: str | os.PathLike) -> Path:
    """Save one image (PNG/JPEG by suffix) atomically."""

    path = Path(path)
    fmt = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}.get(path.suffix.lower())
    if fmt is None:
        raise DataError(f"Cannot save image {path}: use a .png or .jpg suffix.")
    with atomic_path(path) as tmp:
        Image.fromarray(to_uint8(image)).save(tmp, format=fmt)
    return path


def save_image_grid(
    images: Sequence[np.ndarray], path: str | os.PathLike, ncols: int | None = None, gap: int = 2
) -> Path:
    """Tile ``images`` with :func:`image_grid` and save to ``path`` atomically."""
    return save_image(image_grid(images, ncols=ncols, gap=gap), path)
