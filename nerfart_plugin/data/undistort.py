"""Lens undistortion to a pinhole camera: remap tables from pycolmap (any COLMAP model) or OpenCV.

Pixel convention: like COLMAP, nerfstudio and :func:`nerfart_plugin.data.rays.pixel_rays`,
the centre of pixel (column ``u``, row ``v``) is at ``(u + 0.5, v + 0.5)`` in the
coordinates ``K`` maps to. OpenCV puts pixel centres at integer coordinates, so the
OpenCV paths here shift the principal point by -0.5 before building tables, and
every table holds *array index* coordinates ready for ``cv2.remap``.

An undistorted image keeps the image size and the pinhole part of the camera
(``K`` with the model's focal lengths and principal point): output pixel ``q``
shows the ray ``K^-1 [q, 1]``; pixels whose ray falls outside the distorted
image are 0 (black image, background mask).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from nerfart_plugin.errors import DataError

#: COLMAP models that are already pinholes (no remap needed).
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")


@dataclass
class UndistortMaps:
    """Remap tables of one camera.

    Attributes:
        map_x, map_y: float32 [H,W] source column/row (array index coordinates) of
            each output pixel; -10 (reads 0) where the output ray leaves the distorted image.
        K: [3,3] pinhole intrinsics of the undistorted image (pixel centres at +0.5).
        valid_fraction: share of output pixels that sample inside the source image.
        identity: True when the tables move no pixel by more than 1e-3 px.
    """

    map_x: np.ndarray
    map_y: np.ndarray
    K: np.ndarray
    valid_fraction: float
    identity: bool


def _pixel_centres(width: int, height: int) -> np.ndarray:
    """[H*W, 2] pixel centres (u + 0.5, v + 0.5), row-major."""
    v, u = np.meshgrid(np.arange(height, dtype=np.float64) + 0.5, np.arange(width, dtype=np.float64) + 0.5,
                       indexing="ij")
    return np.stack([u.ravel(), v.ravel()], -1)


def _finish(src: np.ndarray, K: np.ndarray, width: int, height: int) -> UndistortMaps:
    """Tables from source pixel coordinates [H*W,2] (pixel centres at +0.5; NaN = no source)."""
    idx = src - 0.5
    inside = np.isfinite(idx).all(-1)
    inside &= (idx[:, 0] >= -0.5) & (idx[:, 0] <= width - 0.5) & (idx[:, 1] >= -0.5) & (idx[:, 1] <= height - 0.5)
    # samples within half a pixel of the border repeat the edge pixel; rays outside read the 0 border
    idx = np.clip(idx, 0.0, [width - 1.0, height - 1.0])
    idx = np.where(inside[:, None], idx, -10.0)
    grid = _pixel_centres(width, height) - 0.5
    moved = np.abs(idx - grid).max() if inside.all() else np.inf
    return UndistortMaps(
        map_x=idx[:, 0].reshape(height, width).astype(np.float32),
        map_y=idx[:, 1].reshape(height, width).astype(np.float32),
        K=np.asarray(K, dtype=np.float64),
        valid_fraction=float(inside.mean()),
        identity=bool(moved < 1e-3),
    )


def colmap_camera(model: str, width: int, height: int, params: Sequence[float], source: str = "") -> Any:
    """A ``pycolmap.Camera``; DataError naming ``source`` for unknown models or wrong parameter counts."""
    import pycolmap

    known = [m for m in pycolmap.CameraModelId.__members__ if m != "INVALID"]
    if model not in known:
        raise DataError(f"{source}: unknown camera model {model!r}; COLMAP models are {', '.join(known)}.")
    cam = pycolmap.Camera(model=model, width=int(width), height=int(height), params=[float(p) for p in params])
    if not cam.verify_params():
        raise DataError(f"{source}: camera model {model} needs parameters ({cam.params_info}), got "
                        f"{len(params)} values {list(params)[:8]}; fix the camera's parameters.")
    return cam


def colmap_maps(camera: Any, source: str = "") -> UndistortMaps:
    """Undistortion tables of a ``pycolmap.Camera`` of any model, through pycolmap's own projection.

    Each output pixel centre ``q`` is lifted to the ray ``K^-1 [q, 1]`` (``K`` =
    ``camera.calibration_matrix()``, the model's pinhole part) and projected with
    ``camera.img_from_cam``, so the table follows whatever lens model COLMAP fitted.

    Raises:
        DataError: spherical models (``EQUIRECTANGULAR``) and models without a focal
            length, which have no pinhole view; tables with fewer than 25% of the
            pixels inside the source image (parameters that do not describe a lens).
    """
    name = camera.model.name
    what = f"{source}: COLMAP camera model {name}"
    if camera.is_spherical() or not list(camera.focal_length_idxs()):
        raise DataError(f"{what} is spherical (360 degree panorama) and has no pinhole view to train on; "
                        "re-run COLMAP with a perspective or fisheye model (e.g. OPENCV, OPENCV_FISHEYE) or "
                        "cut perspective views from the panoramas first.")
    K = np.asarray(camera.calibration_matrix(), dtype=np.float64)
    w, h = int(camera.width), int(camera.height)
    if name in PINHOLE_MODELS:
        return _finish(_pixel_centres(w, h), K, w, h)
    rays = np.concatenate([(_pixel_centres(w, h) - K[:2, 2]) / [K[0, 0], K[1, 1]], np.ones((w * h, 1))], 1)
    try:
        src = np.asarray(camera.img_from_cam(rays), dtype=np.float64)
    except Exception as e:  # pycolmap C++ errors
        raise DataError(f"{what} cannot project points ({e}); it is not supported, use a perspective model.") from e
    maps = _finish(src, K, w, h)
    _check_valid(maps, what)
    return maps


def opencv_maps(K: np.ndarray, dist: Sequence[float], width: int, height: int, fisheye: bool = False,
                source: str = "") -> UndistortMaps:
    """Undistortion tables with OpenCV (``cv2.initUndistortRectifyMap`` / ``cv2.fisheye``), K kept.

    Args:
        K: [3,3] intrinsics, pixel centres at +0.5.
        dist: OpenCV's (k1, k2, p1, p2[, k3[, k4, k5, k6]]) or, for ``fisheye``, (k1, k2, k3, k4).
        width, height: image size in pixels.
    """
    import cv2

    K = np.asarray(K, dtype=np.float64)
    K_cv = K.copy()
    K_cv[:2, 2] -= 0.5  # OpenCV: pixel centres at integers
    D = np.asarray(dist, dtype=np.float64)
    if not np.any(D):
        return _finish(_pixel_centres(width, height), K, width, height)
    try:
        if fisheye:
            mx, my = cv2.fisheye.initUndistortRectifyMap(K_cv, D[:4].reshape(4, 1), np.eye(3), K_cv,
                                                         (int(width), int(height)), cv2.CV_32FC1)
        else:
            mx, my = cv2.initUndistortRectifyMap(K_cv, D, None, K_cv, (int(width), int(height)), cv2.CV_32FC1)
    except cv2.error as e:
        raise DataError(f"{source}: OpenCV cannot build undistortion maps for K={K.tolist()}, "
                        f"distortion={D.tolist()} ({e}); check the camera parameters.") from e
    src = np.stack([mx.ravel(), my.ravel()], -1).astype(np.float64) + 0.5
    maps = _finish(src, K, width, height)
    _check_valid(maps, f"{source}: {'fisheye' if fisheye else 'OpenCV'} distortion {D.tolist()}")
    return maps


def _check_valid(maps: UndistortMaps, what: str) -> None:
    if maps.valid_fraction < 0.25:
        raise DataError(f"{what}: only {maps.valid_fraction:.0%} of the undistorted view falls inside the image; "
                        "the distortion parameters do not describe this lens: re-calibrate the camera.")


def remap(arr: np.ndarray, maps: UndistortMaps) -> np.ndarray:
    """Undistort one image [H,W,C] or [H,W] (float32) with bilinear sampling; outside -> 0."""
    import cv2

    if maps.identity:
        return arr
    out = cv2.remap(np.ascontiguousarray(arr, dtype=np.float32), maps.map_x, maps.map_y, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.reshape(arr.shape)
