"""LLFF ``poses_bounds.npy`` scenes (registry data "llff").

Layout::

    scene/
      poses_bounds.npy     [N,17]: per view a 3x5 matrix (rotation columns
                           [down, right, back], camera centre, [H, W, focal] of the
                           FULL-RESOLUTION originals) flattened, then near/far depths
      images/ images_4/ images_8/ ...   downscaled copies (chosen by ``factor``)
      matte/ (optional)

Forward-facing scenes (all viewing axes within ~60 deg of their mean) are
normalized as in LLFF/NeRF: scaled so the smallest near bound is ``1/bd_factor``
(``bd_factor = 0.75``), then recentred so the average camera is at the origin
looking along **-z** with +y up (the frame :func:`nerfart_plugin.data.rays.ndc_rays`
expects). Render them in NDC (``ndc=True``: ``near_plane=1``, ``t in [0, 1]``).
Other captures become ``"unbounded"``: the cameras' look-at region is put in the
unit sphere (:func:`nerfart_plugin.data.normalize.unit_sphere_from_cameras`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Optional

import numpy as np

from nerfart_plugin.config.components import configured
from nerfart_plugin.config.registry import register
from nerfart_plugin.config.types import Float, Int, Limits, Resolution, Setting
from nerfart_plugin.data.common import make_scene, require_dir
from nerfart_plugin.data.images import (choose_resolution, find_mask_folder, image_size, list_images, match_masks,
    read_image_set)
from nerfart_plugin.data.loader import LoaderConfig, LoaderContext
from nerfart_plugin.data.normalize import apply_similarity, detect_capture, unit_sphere_from_cameras
from nerfart_plugin.data.scene import CaptureType, Scene
from nerfart_plugin.errors import DataError

log = logging.getLogger(__name__)

# LLFF rotation columns are [down, right, back]; OpenCV wants [right, down, forward].
_LLFF_TO_CV = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]], dtype=np.float64)


@dataclass
class PosesBounds:
    """Contents of a ``poses_bounds.npy``.

    Attributes:
        c2w: [N,4,4] OpenCV camera-to-world in the file's world frame.
        hwf: [N,3] (H, W, focal) of the full-resolution originals, pixels.
        bounds: [N,2] near/far scene depths along the viewing axis.
    """

    c2w: np.ndarray
    hwf: np.ndarray
    bounds: np.ndarray


def read_poses_bounds(path: Any) -> PosesBounds:
    """Read and check an LLFF ``poses_bounds.npy`` (no images needed).

    Raises:
        DataError: unreadable, wrong shape, non-finite, bad bounds or rotations.
    """
    path = Path(path)
    fix = f"regenerate {path.name} with LLFF's imgs2poses.py (an [N,17] float array)"
    if not path.is_file():
        raise DataError(f"{path} not found: LLFF scenes need poses_bounds.npy next to the image folders.")
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise DataError(f"Cannot read {path} ({e.__class__.__name__}: {e}); {fix}.") from e
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "fiu":
        raise DataError(f"{path} holds {getattr(arr, 'dtype', type(arr))} data, expected floats; {fix}.")
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] < 1:
        raise DataError(f"{path} has shape {arr.shape}, expected [N,17]; {fix}.")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        bad = np.where(~np.isfinite(arr).all(1))[0][:5].tolist()
        raise DataError(f"{path} has NaN/inf in rows {bad}; {fix}.")
    mats = arr[:, :15].reshape(-1, 3, 5)
    bounds = arr[:, 15:17]
    hwf = mats[:, :, 4]
    if (hwf <= 0).any():
        raise DataError(f"{path}: non-positive H/W/focal in column 4 of some pose; {fix}.")
    if (bounds[:, 0] <= 0).any() or (bounds[:, 1] <= bounds[:, 0]).any():
        raise DataError(f"{path}: bounds must satisfy 0 < near < far for every view; {fix}.")
    R_llff = mats[:, :, :3]
    err = np.abs(np.transpose(R_llff, (0, 2, 1)) @ R_llff - np.eye(3)).max()
    if err > 1e-2 or (np.linalg.det(R_llff) * np.linalg.det(_LLFF_TO_CV) < 0).any():
        raise DataError(f"{path}: pose rotations are not orthonormal/right-handed (error {err:.3g}); {fix}.")
    c2w = np.tile(np.eye(4), (len(arr), 1, 1))
    c2w[:, :3, :3] = R_llff @ _LLFF_TO_CV
    c2w[:, :3, 3] = mats[:, :, 3]
    return PosesBounds(c2w=c2w, hwf=hwf, bounds=bounds)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def llff_average_pose(c2w_cv: np.ndarray) -> np.ndarray:
    """LLFF's ``poses_avg`` as a 4x4 OpenGL-style pose (columns right, up, back, centre)."""
    centre = c2w_cv[:, :3, 3].mean(0)
    back = _normalize(-c2w_cv[:, :3, 2].sum(0))
    up = -c2w_cv[:, :3, 1].sum(0)
    right = _normalize(np.cross(up, back))
    up = _normalize(np.cross(back, right))
    M = np.eye(4)
    M[:3, :4] = np.stack([right, up, back, centre], 1)
    return M


def forward_facing_normalization(c2w_cv: np.ndarray, bounds: np.ndarray, bd_factor: float = 0.75) -> np.ndarray:
    """LLFF normalization ``T`` = recentre(avg pose) @ scale(1 / (min near * bd_factor))."""
    sc = 1.0 / (bounds.min() * bd_factor)
    S = np.diag([sc, sc, sc, 1.0])
    avg = llff_average_pose(apply_similarity(S, c2w_cv))
    return np.linalg.inv(avg) @ S


def _image_folder(root: Path, factor: Optional[int], notes: list[str]) -> tuple[list[Path], Optional[int]]:
    """Image files and the extra downscale still to apply (when only ``images/`` exists)."""
    if factor and factor > 1 and (root / f"images_{factor}").is_dir():
        return list_images(root / f"images_{factor}", notes), None
    if (root / "images").is_dir():
        if factor and factor > 1:
            notes.append(f"images_{factor}/ missing: downscaling images/ by {factor}")
            return list_images(root / "images", notes), factor
        return list_images(root / "images", notes), None
    have = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("images"))
    raise DataError(
        f"No images_{factor}/ or images/ folder in {root} (found {have or 'none'}): set data.factor to one of "
        "the existing images_N folders, or add the images."
    )


class LLFFConfig(LoaderConfig):
    """``data=llff``: an LLFF scene folder (``poses_bounds.npy`` and ``images_<factor>/``)."""

    factor: Optional[Annotated[Int, Limits(ge=1, le=64)]] = Setting(
        8, description="which downscaled folder images_<factor>/ to read (hwf rescaled to its image size); "
        "null: images/")
    resolution: Resolution = Setting(
        "auto", description="auto or null: the native size of images_<factor>/; N: further resize to long side N px")
    bd_factor: Annotated[Float, Limits(gt=0.0, le=10.0)] = Setting(
        0.75, description="LLFF's near-bound margin for forward-facing scenes")
    capture: Optional[CaptureType] = Setting(
        None, description="force object | forward_facing | unbounded instead of detecting it")


@register("data", "llff")
@configured(LLFFConfig)
def load_llff(path: Any, cfg: LLFFConfig, context: Optional[LoaderContext] = None) -> Scene:
    """Load an LLFF scene folder with ``poses_bounds.npy`` and ``images_<factor>/`` (settings: :class:`LLFFConfig`)."""
    capture = cfg.capture  # null: detected below
    root = require_dir(path)
    notes: list[str] = []
    pb_path = root / "poses_bounds.npy"
    pb = read_poses_bounds(pb_path)
    image_paths, extra_factor = _image_folder(root, cfg.factor, notes)
    if len(image_paths) != len(pb.c2w):
        raise DataError(
            f"{pb_path} has {len(pb.c2w)} poses but {image_paths[0].parent} has {len(image_paths)} images; pose i "
            "belongs to the i-th image in sorted order, so the counts must agree: remove the extra images or "
            "re-run imgs2poses.py."
        )
    w_img, h_img = image_size(image_paths[0])
    if extra_factor:
        w_img, h_img = int(round(w_img / extra_factor)), int(round(h_img / extra_factor))
    long_side = choose_resolution(cfg.resolution, (w_img, h_img), notes, cap=None)
    if extra_factor and long_side is None:
        long_side = max(w_img, h_img)
    images, (w0, h0), (w1, h1) = read_image_set(image_paths, long_side)
    H_f, W_f, f = pb.hwf[:, 0], pb.hwf[:, 1], pb.hwf[:, 2]
    sx, sy = w1 / W_f, h1 / H_f
    if abs(W_f[0] / H_f[0] - w0 / h0) > 0.02 * (w0 / h0):
        raise DataError(
            f"Aspect ratio of {image_paths[0]} ({w0}x{h0}) differs from poses_bounds hwf ({W_f[0]:.0f}x{H_f[0]:.0f}): "
            "the images do not belong to these poses (wrong folder?)."
        )
    K = np.zeros((len(f), 3, 3))
    K[:, 0, 0], K[:, 1, 1] = f * sx, f * sy
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = w1 / 2.0, h1 / 2.0, 1.0
    notes.append(
        f"hwf {W_f[0]:.0f}x{H_f[0]:.0f} f={f[0]:.1f} (full resolution) scaled to images {w1}x{h1}: f={f[0] * sx[0]:.2f}"
    )
    masks, mask_paths = None, []
    mask_dir = find_mask_folder(root)
    if cfg.use_masks and mask_dir is not None:
        mask_paths = match_masks(image_paths, list_images(mask_dir, notes), notes)
        masks, _, _ = read_image_set(mask_paths, None, gray=True, what="matte")
        import torch
        import torch.nn.functional as F

        masks = F.interpolate(torch.from_numpy(masks)[:, None], size=(h1, w1), mode="bilinear", antialias=True)[
            :, 0
        ].numpy()
    if capture is None:
        capture, reason = detect_capture(pb.c2w, masks)
    else:
        reason = "set by the capture option"
    if capture == "forward_facing":
        T = forward_facing_normalization(pb.c2w, pb.bounds, cfg.bd_factor)
        notes.append(
            f"capture=forward_facing ({reason}); LLFF normalization: near bound -> {1 / cfg.bd_factor:.3f}, recentred "
            "(mean camera at origin looking along -z); render with data.ndc=true (ndc_rays near_plane=1, t in [0,1])"
        )
    else:
        T = unit_sphere_from_cameras(pb.c2w, near=pb.bounds[:, 0])
        notes.append(f"capture={capture} ({reason}); look-at region scaled into the unit sphere")
    c2w = apply_similarity(T, pb.c2w)
    return make_scene(
        images=images, masks=masks, c2w=c2w, K=K, names=[p.name for p in image_paths], normalization=T,
        capture=capture, source=root, notes=notes, hash_paths=[pb_path, *image_paths, *mask_paths],
        bounds=pb.bounds, holdout_every=cfg.holdout_every,
        opts=dict(kind="llff", factor=cfg.factor, size=(w1, h1), use_masks=cfg.use_masks, bd_factor=cfg.bd_factor,
                  capture=capture))
