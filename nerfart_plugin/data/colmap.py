"""Read a COLMAP sparse model (``cameras.bin/images.bin/points3D.bin`` or ``.txt``) with pycolmap.

Every camera model pycolmap knows is kept as is (model name + parameter vector);
projection and undistortion go through pycolmap's own implementation of the model
(:meth:`ColmapModel.camera`, :func:`nerfart_plugin.data.undistort.colmap_maps`).
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nerfart_plugin.data.undistort import colmap_camera
from nerfart_plugin.errors import DataError

log = logging.getLogger(__name__)


@dataclass
class ColmapModel:
    """A COLMAP reconstruction, images sorted by name.

    Attributes:
        names: image names (relative to the image folder COLMAP used).
        K: [N,3,3] pinhole part of each camera (pixels of the images COLMAP saw,
            pixel centres at +0.5).
        params: per image, the camera's full COLMAP parameter vector (model order,
            e.g. OPENCV: fx, fy, cx, cy, k1, k2, p1, p2).
        sizes: [N,2] (W, H) per image.
        c2w: [N,4,4] OpenCV camera-to-world in the model's frame.
        points: [P,3] sparse 3D points; colors [P,3] uint8; errors [P] (px).
        observations: per image, (xy [M,2] pixels, point index [M] into ``points``).
        camera_models: COLMAP model name per image (any model pycolmap knows).
        camera_ids: COLMAP camera id per image (images sharing a camera share it).
    """

    names: list[str]
    K: np.ndarray
    params: list[np.ndarray]
    sizes: np.ndarray
    c2w: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    errors: np.ndarray
    observations: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    camera_models: list[str] = field(default_factory=list)
    camera_ids: list[int] = field(default_factory=list)

    def camera(self, i: int) -> Any:
        """The ``pycolmap.Camera`` of image ``i`` (projection through its lens model)."""

        w, h = (int(x) for x in self.sizes[i])
        return colmap_camera(self.camera_models[i], w, h, self.params[i], source=self.names[i])


def _model_name(cam: Any) -> str:
    return cam.model.name if hasattr(cam.model, "name") else str(cam.model)


def _walk(data: bytes, name: str, head: str, per_item: int, named: bool = False) -> None:
    """Walk the records of a COLMAP binary file (a uint64 record count, then the records): each record has
    fixed fields (``head``, a little-endian struct format), a NUL-terminated name when ``named``, a uint64
    list length and that many entries of ``per_item`` bytes. Raises DataError when a record claims more bytes
    than the file holds."""

    if len(data) < 8:
        raise DataError(f"{name} is {len(data)} bytes, too short for a COLMAP model")
    (n,) = struct.unpack_from("<Q", data, 0)
    pos, size = 8, struct.calcsize(head)
    for i in range(n):
        if pos + size > len(data):
            raise DataError(f"{name} declares {n} records but ends inside record {i}")
        pos += size
        if named:
            end = data.find(b"\0", pos)
            if end < 0:
                raise DataError(f"{name}: record {i} has no end to its name")
            pos = end + 1
        if pos + 8 > len(data):
            raise DataError(f"{name}: record {i} ends before its list length")
        (k,) = struct.unpack_from("<Q", data, pos)
        pos += 8 + k * per_item
        if pos > len(data):
            raise DataError(f"{name}: record {i} declares {k} entries, more than the file holds")


def check_binary_lengths(path: Path, fix: str) -> None:
    """Refuse ``images.bin`` / ``points3D.bin`` whose records claim more data than the files hold (a corrupt
    list length makes pycolmap read past the end for up to 2^64 entries: a hang, not an error)."""
    try:
        # images.bin: image_id, qvec[4], tvec[3], camera_id, name\0, num_points2D, (x, y, point3D_id) each
        _walk((path / "images.bin").read_bytes(), "images.bin", "<I4d3dI", 24, named=True)
        # points3D.bin: point3D_id, xyz[3], rgb[3], error, track_length, (image_id, point2D_idx) each
        _walk((path / "points3D.bin").read_bytes(), "points3D.bin", "<Q3d3Bd", 8)
    except DataError as exc:
        raise DataError(f"Cannot read COLMAP model {path} ({exc}); {fix}.") from None


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
    if {"images.bin", "points3D.bin"} <= have:
        check_binary_lengths(path, fix)
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
    Ks, params, sizes, c2ws, obs, models = [], [], [], [], [], []
    for im in images:
        cam = rec.cameras[im.camera_id]
        if not cam.verify_params() or not np.isfinite(np.asarray(cam.params, dtype=np.float64)).all():
            raise DataError(f"COLMAP model {source}: camera {im.camera_id} ({_model_name(cam)}) has invalid "
                            f"parameters {list(cam.params)[:8]}; {fix}.")
        K = np.asarray(cam.calibration_matrix(), dtype=np.float64) if list(cam.focal_length_idxs()) else np.eye(3)
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
        params.append(np.asarray(cam.params, dtype=np.float64))
        sizes.append((cam.width, cam.height))
        c2ws.append(c2w)
        models.append(_model_name(cam))
    if not np.isfinite(pts).all():
        raise DataError(f"COLMAP model {source} has non-finite 3D points; {fix}.")
    return ColmapModel(
        names=[im.name for im in images],
        K=np.stack(Ks),
        params=params,
        sizes=np.array(sizes, dtype=np.int64),
        c2w=np.stack(c2ws),
        points=pts,
        colors=cols,
        errors=errs,
        observations=obs,
        camera_models=models,
        camera_ids=[int(im.camera_id) for im in images],
    )


def project(points: np.ndarray, K: np.ndarray, c2w: np.ndarray, camera: Any = None) -> np.ndarray:
    """Project world points [P,3] into a camera -> pixels [P,2] (pixel centres at +0.5, as COLMAP).

    Args:
        points: [P,3] world points.
        K: [3,3] pinhole intrinsics, used when ``camera`` is None.
        c2w: [4,4] OpenCV camera-to-world.
        camera: optional ``pycolmap.Camera``: project through its lens model
            (``img_from_cam``, any COLMAP model) instead of the pinhole ``K``.
    """
    w2c = np.linalg.inv(c2w)
    X = points @ w2c[:3, :3].T + w2c[:3, 3]
    if camera is not None:
        return np.asarray(camera.img_from_cam(X.astype(np.float64)), dtype=np.float64).reshape(-1, 2)
    uvw = X @ np.asarray(K, dtype=np.float64).T
    return uvw[:, :2] / uvw[:, 2:3]


def reprojection_errors(model: ColmapModel) -> np.ndarray:
    """Pixel distances between every observation and its projected 3D point (through the lens model), [M_total]."""
    errs = []
    for i, (xy, idx) in enumerate(model.observations):
        if len(idx):
            uv = project(model.points[idx], model.K[i], model.c2w[i], model.camera(i))
            errs.append(np.linalg.norm(uv - xy, axis=-1))
    return np.concatenate(errs) if errs else np.zeros(0)
