"""IDR / VolSDF ``cameras.npz`` and NeuS ``cameras_sphere.npz`` scenes (registry data "h3ds").

Layout::

    scene/
      cameras.npz | cameras_sphere.npz   world_mat_i (K[R|t] projection, 4x4 or 3x4),
                                         scale_mat_i (4x4 normalization), i = 0..N-1
      images/ | image/  *.png|*.jpg      camera i <-> i-th image in sorted order
      matte/ | mask/ | masks/ (optional) foreground mattes

Both naming schemes load: the NeRF-Art/VolSDF one (``images/``, ``matte/``,
``cameras.npz``) and the NeuS/IDR/DTU one (``image/``, ``mask/``,
``cameras_sphere.npz``), in any mix.

The camera of view ``i`` is recovered from ``P = world_mat_i @ scale_mat_i`` by an
RQ decomposition (``cv2.decomposeProjectionMatrix``), as IDR's
``load_K_Rt_from_P`` does; ``scale_mat`` maps the unit sphere onto the object, so
the returned frame has the object inside the unit sphere.
"""

from __future__ import annotations

import logging
import re
import zipfile
from pathlib import Path
from typing import Any, Optional

import numpy as np

from nerfart_plugin.config.components import configured
from nerfart_plugin.config.registry import register
from nerfart_plugin.config.types import Setting
from nerfart_plugin.data.common import make_scene, require_dir
from nerfart_plugin.data.images import (choose_resolution, find_mask_folder, image_size, list_images, match_masks,
    read_image_set)
from nerfart_plugin.data.loader import LoaderConfig, LoaderContext
from nerfart_plugin.data.normalize import detect_capture
from nerfart_plugin.data.scene import Scene
from nerfart_plugin.errors import DataError

log = logging.getLogger(__name__)

CAMERA_FILES = ("cameras.npz", "cameras_sphere.npz")
#: image folder names, in order of preference (VolSDF/NeRF-Art, NeuS/IDR/DTU)
IMAGE_FOLDERS = ("images", "image")


def find_image_folder(root: Path) -> Path:
    """``images/`` or ``image/`` under ``root``; DataError listing what was looked for."""
    for name in IMAGE_FOLDERS:
        if (root / name).is_dir():
            return root / name
    have = sorted(p.name + "/" for p in root.iterdir() if p.is_dir())
    raise DataError(
        f"No image folder in {root}: looked for {' or '.join(n + '/' for n in IMAGE_FOLDERS)} (found "
        f"{', '.join(have) or 'no folders'}); put the views in images/ (or NeuS's image/)."
    )


def load_K_Rt_from_P(P: np.ndarray, source: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Split a 3x4 projection ``P = K [R | t]`` into ``K`` [3,3] and OpenCV ``c2w`` [4,4].

    Raises:
        DataError: singular or non-finite ``P``.
    """
    import cv2

    P = np.asarray(P, dtype=np.float64)[:3, :4]
    if not np.isfinite(P).all() or np.linalg.matrix_rank(P[:3, :3]) < 3:
        raise DataError(f"Projection matrix {source} is singular or not finite; regenerate the cameras file.")
    try:
        K, R, t = cv2.decomposeProjectionMatrix(P)[:3]
    except cv2.error as e:  # pragma: no cover - guarded by the rank check
        raise DataError(f"Cannot decompose projection matrix {source}: {e}") from e
    if abs(K[2, 2]) < 1e-12 or abs(t[3, 0]) < 1e-12:
        raise DataError(f"Degenerate projection matrix {source}; regenerate the cameras file.")
    K = K / K[2, 2]
    c2w = np.eye(4)
    c2w[:3, :3] = R.T
    c2w[:3, 3] = (t[:3] / t[3])[:, 0]
    if not (np.isfinite(K).all() and np.isfinite(c2w).all()) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DataError(f"Projection matrix {source} gives invalid intrinsics {K.tolist()}.")
    return K, c2w


def read_cameras_npz(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read ``world_mat_i``/``scale_mat_i`` for i = 0..N-1.

    Returns:
        K [N,3,3] (pixels of the images the file was made for), c2w [N,4,4] OpenCV
        in the normalized (unit-sphere) frame, scale_mats [N,4,4].

    Raises:
        DataError: unreadable file, missing/non-contiguous keys, wrong shapes, NaN.
    """
    path = Path(path)
    fix = f"regenerate {path.name} (IDR/VolSDF/NeuS format: world_mat_i and scale_mat_i, 4x4, i=0..N-1)"
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: np.asarray(data[k]) for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as e:
        raise DataError(f"Cannot read camera file {path} ({e.__class__.__name__}: {e}); {fix}.") from e
    idx = sorted(int(m.group(1)) for k in arrays if (m := re.fullmatch(r"world_mat_(\d+)", k)))
    if not idx:
        raise DataError(f"{path} has no world_mat_i keys (found {sorted(arrays)[:6]}); {fix}.")
    if idx != list(range(len(idx))):
        missing = sorted(set(range(max(idx) + 1)) - set(idx))[:5]
        raise DataError(f"{path}: world_mat indices are not 0..{len(idx) - 1} (missing {missing}); {fix}.")
    Ks, c2ws, scales = [], [], []
    for i in idx:
        W = arrays[f"world_mat_{i}"]
        S = arrays.get(f"scale_mat_{i}", np.eye(4))
        for name, M in ((f"world_mat_{i}", W), (f"scale_mat_{i}", S)):
            if M.dtype.kind not in "fiu" or M.shape not in ((4, 4), (3, 4)):
                raise DataError(f"{path}: {name} has shape {M.shape} dtype {M.dtype}, expected 4x4 numbers; {fix}.")
            if not np.isfinite(M).all():
                raise DataError(f"{path}: {name} contains NaN/inf; {fix}.")
        W = np.vstack([W, [0, 0, 0, 1]]) if W.shape == (3, 4) else W
        S = np.vstack([S, [0, 0, 0, 1]]) if S.shape == (3, 4) else S
        S = S.astype(np.float64)
        if abs(np.linalg.det(S[:3, :3])) < 1e-12:
            raise DataError(f"{path}: scale_mat_{i} is singular; {fix}.")
        K, c2w = load_K_Rt_from_P((W.astype(np.float64) @ S)[:3, :4], f"world_mat_{i} @ scale_mat_{i} in {path}")
        Ks.append(K)
        c2ws.append(c2w)
        scales.append(S)
    if "scale_mat_0" not in arrays:
        log.info("%s has no scale_mat_i: using identity (no normalization)", path)
    return np.stack(Ks), np.stack(c2ws), np.stack(scales)


class H3DSConfig(LoaderConfig):
    """``data=h3ds``: an IDR / VolSDF / NeuS scene folder."""

    cameras_file: Optional[str] = Setting(
        None, description="the cameras npz inside the folder; null: cameras.npz, else cameras_sphere.npz")


@register("data", "h3ds")
@configured(H3DSConfig)
def load_h3ds(path: Any, cfg: H3DSConfig, context: Optional[LoaderContext] = None) -> Scene:
    """Load an IDR/VolSDF/NeuS scene folder: ``images/`` or ``image/``, ``cameras.npz`` or
    ``cameras_sphere.npz``, optional ``matte/``/``mask/`` (settings: :class:`H3DSConfig`; "auto" resolution
    keeps the 256x256 head native, see :func:`~nerfart_plugin.data.images.choose_resolution`).

    Returns:
        a validated :class:`Scene`.
    """
    root = require_dir(path)
    notes: list[str] = []
    if cfg.cameras_file is not None:
        cam_path = root / cfg.cameras_file
        if not cam_path.is_file():
            raise DataError(f"Camera file {cam_path} not found: fix data.cameras_file (have: {list(CAMERA_FILES)}).")
    else:
        found = [root / f for f in CAMERA_FILES if (root / f).is_file()]
        if not found:
            raise DataError(
                f"No cameras.npz or cameras_sphere.npz in {root}: this loader needs IDR/VolSDF/NeuS cameras; "
                "for LLFF poses_bounds.npy use data=llff, for a video or COLMAP model use data=selfie."
            )
        cam_path = found[0]
    image_dir = find_image_folder(root)
    image_paths = list_images(image_dir, notes)
    Ks, c2w, scales = read_cameras_npz(cam_path)
    if len(Ks) != len(image_paths):
        raise DataError(
            f"{cam_path} has {len(Ks)} cameras but {image_dir} has {len(image_paths)} images; camera i is "
            "paired with the i-th image in sorted order, so the counts must agree: remove the images without "
            "cameras (or regenerate the cameras file for all images)."
        )
    long_side = choose_resolution(cfg.resolution, image_size(image_paths[0]), notes)
    images, (w0, h0), (w1, h1) = read_image_set(image_paths, long_side)
    sx, sy = w1 / w0, h1 / h0
    if (w1, h1) != (w0, h0):
        Ks = Ks.copy()
        Ks[:, 0, :] *= sx
        Ks[:, 1, :] *= sy
        notes.append(f"resized images {w0}x{h0} -> {w1}x{h1}; intrinsics scaled by ({sx:.4f}, {sy:.4f})")
    masks = None
    mask_paths: list[Path] = []
    mask_dir = find_mask_folder(root)
    if cfg.use_masks and mask_dir is not None:
        mask_paths = match_masks(image_paths, list_images(mask_dir, notes), notes)
        masks, (mw, mh), _ = read_image_set(mask_paths, long_side, gray=True, what="matte")
        if (mw, mh) != (w0, h0):
            raise DataError(
                f"Mattes in {mask_dir} are {mw}x{mh} but images are {w0}x{h0}: resize the mattes to the image size."
            )
    elif cfg.use_masks:
        notes.append("no matte/ or mask/ folder: loading without masks")
    capture, reason = detect_capture(c2w, masks)
    layout = f"views from {image_dir.name}/" + (f", mattes from {mask_dir.name}/" if mask_paths else "")
    notes.append(f"capture={capture}: {reason}; unit sphere from scale_mat of {cam_path.name}; {layout}")
    return make_scene(  # no depth bounds: the unit sphere (from scale_mat) around each camera
        images=images, masks=masks, c2w=c2w, K=Ks, names=[p.name for p in image_paths],
        normalization=np.linalg.inv(scales[0]), capture=capture, source=root, notes=notes,
        hash_paths=[cam_path, *image_paths, *mask_paths], holdout_every=cfg.holdout_every,
        opts=dict(kind="h3ds", size=(w1, h1), use_masks=cfg.use_masks, cameras=cam_path.name))
