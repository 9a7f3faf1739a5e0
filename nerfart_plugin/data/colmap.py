"""Read a COLMAP sparse model (``cameras.bin/images.bin/points3D.bin`` or ``.txt``) with pycolmap."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nerfart_plugin.errors import DataError

log = logging.getLogger(__name__)

# Distortion parameters (in pycolmap's params order after fx/fy/cx/cy) -> OpenCV's
# (k1, k2, p1, p2, k3) vector. Models not listed are treated as undistorted pinholes.
_DIST_MODELS = {
    "SIMPLE_RADIAL": lambda p: [p[3], 0, 0, 0],
    "RADIAL": lambda p: [p[3], p[4], 0, 0],
    "OPENCV": lambda p: [p[4], p[5], p[6], p[7]],
    "FULL_OPENCV": lambda p: [p[4], p[5], p[6], p[7], p[8]],
}


@dataclass
class ColmapModel:
    """A COLMAP reconstruction, images sorted by name.

    Attributes:
        names: image names (relative to the image folder COLMAP used).
        K: [N,3,3] pinhole intrinsics (pixels of the images COLMAP saw).
        dist: [N,k] OpenCV distortion coefficients (zeros for pinhole models).
        sizes: [N,2] (W, H) per image.
        c2w: [N,4,4] OpenCV camera-to-world in the model's frame.
        points: [P,3] sparse 3D points; colors [P,3] uint8; errors [P] (px).
        observations: per image, (xy [M,2] pixels, point index [M] into ``points``).
        camera_models: COLMAP model name per image.
    """

    names: list[str]
    K: np.ndarray
    dist: np.ndarray
    sizes: np.ndarray
    c2w: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    errors: np.ndarray
    observations: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    camera_models: list[str] = field(default_factory=list)


def _params(cam: Any) -> tuple[np.ndarray, np.ndarray]:
    name = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
    p = np.asarray(cam.params, dtype=np.float64)
    K = np.asarray(cam.calibration_matrix(), dtype=np.float64)
    d = _DIST_MODELS.get(name)
    dist = np.asarray(d(p) if d else [0, 0, 0, 0], dtype=np.float64)
    if dist.size == 4:
        dist = np.concatenate([dist, [0.0]])
    return K, dist


def read_colmap_model(path: Any) -> ColmapModel:
    """Load a COLMAP sparse model folder (e.g. ``scene/sparse/0``).

    Raises:
        DataError: missing folder/files, unreadable or empty model, NaN poses.
    """
    import pycolmap

    path = Path(path)
    fix = "re-run COLMAP (or data=selfie on the frames) to rebuild the sparse model"
    if not path.is_dir():
        raise DataError(f"COLMAP model folder {path} does not exist; {fix}.")
    have = {p.name for p in path.iterdir()}
    if not ({"cameras.bin", "images.bin", "points3D.bin"} <= have or {"cameras.txt", "images.txt", "points3D.txt"} <= have):
        raise DataError(
            f"{path} is not a COLMAP sparse model (needs cameras/images/points3D .bin or .txt, found "
            f"{sorted(have)[:6]}); {fix}."
        )
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as e:  # pycolmap raises assorted C++ exceptions for corrupt files
        raise DataError(f"Cannot read COLMAP model {path} ({e.__class__.__name__}: {str(e)[:200]}); {fix}.") from e
    return model_from_reconstruction(rec, str(path))


def model_from_reconstruction(rec: Any, source: str = "reconstruction") -> ColmapModel:
    """Convert a ``pycolmap.Reconstruction`` to a :class:`ColmapModel`."""
    fix = "re-run COLMAP (or data=selfie on the frames) to rebuild the sparse model"
    try:
        images = sorted(
            (im for im in rec.images.values() if (im.has_pose if isinstance(im.has_pose, bool) else im.has_pose())),
            key=lambda im: im.name,
        )
    except Exception as e:
        raise DataError(f"Cannot read images of COLMAP model {source} ({e}); {fix}.") from e
    if not images:
        raise DataError(f"COLMAP model {source} has no registered images; {fix}.")
    pid_list = list(rec.points3D.keys())
    pid_index = {pid: i for i, pid in enumerate(pid_list)}
    if pid_list:
        pts = np.stack([np.asarray(rec.points3D[p].xyz, dtype=np.float64) for p in pid_list])
        cols = np.stack([np.asarray(rec.points3D[p].color, dtype=np.uint8) for p in pid_list])
        errs = np.array([rec.points3D[p].error for p in pid_list], dtype=np.float64)
    else:
        pts, cols, errs = np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0)
    Ks, dists, sizes, c2ws, obs, models = [], [], [], [], [], []
    for im in images:
        cam = rec.cameras[im.camera_id]
        K, dist = _params(cam)
        cfw = im.cam_from_world
        cfw = cfw() if callable(cfw) else cfw
        M = np.eye(4)
        M[:3, :4] = np.asarray(cfw.matrix(), dtype=np.float64)
        c2w = np.linalg.inv(M)
        if not (np.isfinite(c2w).all() and np.isfinite(K).all()) or K[0, 0] <= 0:
            raise DataError(f"COLMAP model {source}: invalid pose or camera for image {im.name}; {fix}.")
        xy, idx = [], []
        for p2 in im.points2D:
            if p2.has_point3D():
                j = pid_index.get(p2.point3D_id)
                if j is not None:
                    xy.append(np.asarray(p2.xy, dtype=np.float64))
                    idx.append(j)
        obs.append((np.array(xy).reshape(-1, 2), np.array(idx, dtype=np.int64)))
        Ks.append(K)
        dists.append(dist)
        sizes.append((cam.width, cam.height))
        c2ws.append(c2w)
        models.append(cam.model.name if hasattr(cam.model, "name") else str(cam.model))
    if not np.isfinite(pts).all():
        raise DataError(f"COLMAP model {source} has non-finite 3D points; {fix}.")
    return ColmapModel(
        names=[im.name for im in images],
        K=np.stack(Ks),
        dist=np.stack(dists),
        sizes=np.array(sizes, dtype=np.int64),
        c2w=np.stack(c2ws),
        points=pts,
        colors=cols,
        errors=errs,
        observations=obs,
        camera_models=models,
    )


def project(points: np.ndarray, K: np.ndarray, c2w: np.ndarray, dist: np.ndarray | None = None) -> np.ndarray:
    """Project world points [P,3] into a camera (OpenCV model incl. distortion) -> pixels [P,2].

    Pixel coordinates follow COLMAP/OpenCV: the centre of pixel (u, v) is at
    (u + 0.5, v + 0.5) for COLMAP; both conventions agree since K comes from it.
    """
    w2c = np.linalg.inv(c2w)
    X = points @ w2c[:3, :3].T + w2c[:3, 3]
    x, y = X[:, 0] / X[:, 2], X[:, 1] / X[:, 2]
    if dist is not None and np.any(dist):
        k1, k2, p1, p2, k3 = (list(dist) + [0.0] * 5)[:5]
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        x, y = (
            x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
        )
    u = K[0, 0] * x + K[0, 1] * y + K[0, 2]
    v = K[1, 1] * y + K[1, 2]
    return np.stack([u, v], -1)


def reprojection_errors(model: ColmapModel) -> np.ndarray:
    """Pixel distances between every observation and its projected 3D point, [M_total]."""
    errs = []
    for i, (xy, idx) in enumerate(model.observations):
        if len(idx):
            uv = project(model.points[idx], model.K[i], model.c2w[i], model.dist[i])
            errs.append(np.linalg.norm(uv - xy, axis=-1))
    return np.concatenate(errs) if errs else np.zeros(0)
