"""Image/matte listing, reading and resizing shared by the loaders.

Every failure is a :class:`~nerfart_plugin.errors.DataError` naming the file and
the fix.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
from PIL import Image

from nerfart_plugin.errors import ConfigError, DataError

log = logging.getLogger(__name__)

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")

#: ``data.resolution=auto`` loads images with the long side min(native, AUTO_LONG_SIDE): the
#: paper's selfies at 270x480, the 256x256 H3DS head and other small captures at their native size.
AUTO_LONG_SIDE = 480


def choose_resolution(
    resolution: Any, native: tuple[int, int], notes: list[str], cap: Optional[int] = AUTO_LONG_SIDE
) -> Optional[int]:
    """The long side to load images at, from ``data.resolution``; logged and noted with the reason.

    Args:
        resolution: ``"auto"`` (long side ``min(native, cap)``; native when ``cap`` is
            None, as for LLFF, whose ``factor`` picks the size), ``None``/``"native"``
            (native size) or a positive integer (long side in pixels, overrides).
        native: (W, H) of the images as stored.
        notes: the scene notes to append the choice to.
        cap: the long-side cap of ``auto`` (:data:`AUTO_LONG_SIDE`).

    Returns:
        the long side in pixels, or None for the native size.

    Raises:
        ConfigError: any other value.
    """
    w, h = int(native[0]), int(native[1])
    long_native = max(w, h)
    if isinstance(resolution, str) and resolution.strip().lower() in ("auto", "native", "null", "none"):
        resolution = resolution.strip().lower()
    elif resolution is not None:
        ok = isinstance(resolution, (int, np.integer)) and not isinstance(resolution, bool) and resolution > 0
        if not ok:
            raise ConfigError(
                f"data.resolution={resolution!r} is not valid: use auto (long side min(native, "
                f"{AUTO_LONG_SIDE}) px), null (native size) or a positive integer (the long side in pixels)."
            )
        resolution = int(resolution)
    if resolution in (None, "native", "null", "none"):
        long_side, why = None, f"data.resolution=null: native {w}x{h}"
    elif resolution == "auto":
        if cap is None or long_native <= cap:
            long_side = None
            why = f"data.resolution=auto: native {w}x{h}" + (f" (long side <= {cap} px)" if cap else "")
        else:
            long_side = cap
            why = (f"data.resolution=auto: long side {cap} px, {w}x{h} -> {'x'.join(map(str, target_size(w, h, cap)))} "
                   f"(min(native, {cap}) as the paper's 270x480 selfies)")
    else:
        long_side = resolution
        why = f"data.resolution={resolution}: {w}x{h} -> {'x'.join(map(str, target_size(w, h, resolution)))}"
        if resolution > long_native:
            why += " (upsampled: larger than the images)"
    log.info("resolution: %s", why)
    notes.append(f"resolution: {why}; data.resolution=<long side>|null|auto to change")
    return long_side if long_side != long_native else None


def list_images(folder: Path, notes: Optional[list[str]] = None) -> list[Path]:
    """Sorted image files in ``folder``; other files are skipped and noted.

    Raises:
        DataError: folder missing or holding no image.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"Image folder {folder} does not exist: point data.path at a scene folder that contains it.")
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    images = [p for p in files if p.suffix.lower() in IMAGE_EXTS]
    others = [p.name for p in files if p.suffix.lower() not in IMAGE_EXTS]
    if others and notes is not None:
        msg = f"ignored {len(others)} non-image file(s) in {folder.name}/: {', '.join(others[:5])}"
        notes.append(msg)
    if not images:
        raise DataError(
            f"No images ({'/'.join(IMAGE_EXTS)}) found in {folder}: put the views there or fix data.path."
        )
    return images


def target_size(w: int, h: int, resolution: Optional[int]) -> tuple[int, int]:
    """(W', H') with the long side equal to ``resolution`` (unchanged if None)."""
    if not resolution:
        return w, h
    s = float(resolution) / max(w, h)
    return max(1, int(round(w * s))), max(1, int(round(h * s)))


def read_image(path: Path, size: Optional[tuple[int, int]] = None, gray: bool = False) -> np.ndarray:
    """Read an image as float32 in [0,1]: [H,W,3] (or [H,W] when ``gray``).

    Resizing to ``size`` = (W, H) uses an antialiasing (Lanczos/box) filter.

    Raises:
        DataError: unreadable, truncated or zero-length file.
    """
    path = Path(path)
    try:
        with Image.open(path) as im:
            im.load()
            if gray:
                im = im.convert("L") if im.mode not in ("L", "I;16", "I", "F") else im
                if im.mode != "L":
                    arr = np.asarray(im, dtype=np.float32)
                    im = Image.fromarray((arr / max(arr.max(), 1.0) * 255).astype(np.uint8))
            else:
                im = im.convert("RGB")
            if size is not None and im.size != tuple(size):
                im = im.resize(tuple(size), Image.Resampling.LANCZOS)
            arr = np.asarray(im, dtype=np.float32) / 255.0
    except (OSError, ValueError, SyntaxError) as e:
        raise DataError(
            f"Cannot read image {path} ({e.__class__.__name__}: {e}): the file is corrupt or truncated; "
            "re-export or delete it (and its camera) from the scene."
        ) from e
    return np.clip(arr, 0.0, 1.0)


def image_size(path: Path) -> tuple[int, int]:
    """(W, H) from the header; DataError for unreadable files."""
    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, ValueError, SyntaxError) as e:
        raise DataError(f"Cannot read image {path} ({e}): the file is corrupt; re-export or remove it.") from e


def read_image_set(
    paths: Sequence[Path], resolution: Optional[int], gray: bool = False, what: str = "image"
) -> tuple[np.ndarray, tuple[int, int], tuple[int, int]]:
    """Read images of one common size, resized so the long side is ``resolution``.

    Returns:
        (array [N,H',W',3] or [N,H',W'], original (W,H), new (W',H')).

    Raises:
        DataError: mixed sizes (naming an offending file) or unreadable files.
    """
    sizes = [image_size(p) for p in paths]
    first = sizes[0]
    for p, s in zip(paths, sizes):
        if s != first:
            raise DataError(
                f"Mixed {what} sizes: {paths[0].name} is {first[0]}x{first[1]} but {p} is {s[0]}x{s[1]}; "
                "all views of a scene must share one size: resize or remove the odd one(s)."
            )
    new = target_size(first[0], first[1], resolution)
    arr = np.stack([read_image(p, new, gray=gray) for p in paths])
    return arr, first, new


def find_mask_folder(root: Path) -> Optional[Path]:
    """``matte/`` or ``mask/`` (or ``masks/``) under ``root`` if present."""
    for name in ("matte", "mask", "masks"):
        if (root / name).is_dir():
            return root / name
    return None


def match_masks(images: Sequence[Path], mask_files: Sequence[Path], notes: list[str]) -> list[Path]:
    """Pick the matte for each image.

    Same count -> by sorted order. Otherwise by file stem (``000001.png`` image ->
    ``000001.png`` matte); extra mattes are ignored and noted.

    Raises:
        DataError: when some image has no matte that can be identified.
    """
    if len(mask_files) == len(images):
        return list(mask_files)
    by_stem = {p.stem: p for p in mask_files}
    missing = [p.name for p in images if p.stem not in by_stem]
    folder = mask_files[0].parent if mask_files else "?"
    if missing:
        raise DataError(
            f"{len(images)} images but {len(mask_files)} mattes in {folder}, and the mattes cannot be matched "
            f"by name (no matte for {', '.join(missing[:3])}); give each image a matte of the same name, "
            "or set data.use_masks=false."
        )
    chosen = [by_stem[p.stem] for p in images]
    extra = sorted(set(p.name for p in mask_files) - set(p.name for p in chosen))
    msg = (
        f"{len(mask_files)} mattes for {len(images)} images in {Path(folder).name}/: matched by file name, "
        f"ignored {len(extra)} extra matte(s) ({', '.join(extra[:5])}{'...' if len(extra) > 5 else ''})"
    )
    notes.append(msg)
    return chosen


def read_rgba(path: Path) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Read an image at its native size as float32 in [0,1]: (rgb [H,W,3], alpha [H,W] or None).

    Images with an alpha channel (RGBA, LA, palette with transparency) return their
    alpha; the RGB values are the stored (straight, not premultiplied) colours.

    Raises:
        DataError: unreadable, truncated or zero-length file.
    """
    path = Path(path)
    try:
        with Image.open(path) as im:
            im.load()
            has_alpha = im.mode in ("RGBA", "LA", "PA", "La", "RGBa") or (
                im.mode == "P" and "transparency" in im.info)
            arr = np.asarray(im.convert("RGBA" if has_alpha else "RGB"), dtype=np.float32) / 255.0
    except (OSError, ValueError, SyntaxError) as e:
        raise DataError(
            f"Cannot read image {path} ({e.__class__.__name__}: {e}): the file is corrupt or truncated; "
            "re-export or delete it (and its frame) from the scene."
        ) from e
    return (arr[..., :3], arr[..., 3]) if has_alpha else (arr, None)


def resize_float(arr: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize a float image [H,W] or [H,W,C] to ``size`` = (W, H) with Lanczos per channel, clipped to [0,1]."""
    if (arr.shape[1], arr.shape[0]) == tuple(size):
        return arr
    chans = arr[..., None] if arr.ndim == 2 else arr
    out = np.stack([np.asarray(Image.fromarray(np.ascontiguousarray(chans[..., c], dtype=np.float32))
                               .resize(tuple(size), Image.Resampling.LANCZOS)) for c in range(chans.shape[-1])], -1)
    out = np.clip(out, 0.0, 1.0)
    return out[..., 0] if arr.ndim == 2 else out


def resize_premultiplied(rgb: np.ndarray, alpha: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Resize straight-alpha ``rgb`` [H,W,3] and ``alpha`` [H,W] without dark fringes (premultiplied filtering).

    Returns straight colours again (0 where the resized alpha is 0) and the resized alpha.
    """
    if (rgb.shape[1], rgb.shape[0]) == tuple(size):
        return rgb, alpha
    a = resize_float(alpha, size)
    pre = resize_float(rgb * alpha[..., None], size)
    straight = np.where(a[..., None] > 1e-4, pre / np.maximum(a[..., None], 1e-4), 0.0)
    return np.clip(straight, 0.0, 1.0).astype(np.float32), a
