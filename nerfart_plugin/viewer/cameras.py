"""Cameras between the browser and the field: viser's camera <-> the project's OpenCV cameras.

viser reports each browser tab's camera as a rotation ``wxyz`` and a ``position`` with ``P_world =
R p_camera + t`` in OpenCV axes (x right, y down, looking down +z), a vertical field of view (radians)
and the canvas' aspect ratio (width / height). The viewer shows the capture's **world frame** (that of
the exported meshes, ``cameras.json`` and ``camera_path.json``); the field is rendered in the
normalized (training) frame, so a camera crosses :meth:`CaptureCameras.from_world` on its way to the
renderer. Pixels are square and the principal point is centred (as in nerfstudio's viewer).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from viser.transforms import SO3

from nerfart_plugin.cameras.capture import CaptureCameras
from nerfart_plugin.cameras.path import RenderPath

#: the field of view a camera may have (radians, vertical)
FOV_RANGE = (math.radians(1.0), math.radians(170.0))


@dataclass(frozen=True)
class ViewCamera:
    """One viewing camera in the capture's world frame.

    Attributes:
        c2w: [3,4] OpenCV camera-to-world (world units of the capture).
        fov_y: vertical field of view, radians.
        aspect: image width / height.
    """

    c2w: np.ndarray
    fov_y: float
    aspect: float

    def size(self, long_side: int) -> tuple[int, int]:
        """(H, W) pixels with the long side at ``long_side``."""
        long_side = max(int(long_side), 1)
        if self.aspect >= 1.0:
            return max(1, round(long_side / self.aspect)), long_side
        return long_side, max(1, round(long_side * self.aspect))

    def intrinsics(self, H: int, W: int) -> np.ndarray:
        """[3,3] pinhole intrinsics at H x W: square pixels, centred principal point."""
        f = 0.5 * H / math.tan(0.5 * self.fov_y)
        return np.array([[f, 0.0, 0.5 * W], [0.0, f, 0.5 * H], [0.0, 0.0, 1.0]])

    def key(self, decimals: int = 6) -> tuple:
        """A hashable summary: two cameras with the same key render the same frame."""
        return (tuple(np.round(self.c2w, decimals).ravel()), round(self.fov_y, decimals), round(self.aspect, decimals))


def wxyz_to_matrix(wxyz: np.ndarray) -> np.ndarray:
    """[3,3] rotation of the quaternion ``(w, x, y, z)`` (normalized first)."""
    q = np.asarray(wxyz, dtype=np.float64)
    return SO3(q / max(float(np.linalg.norm(q)), 1e-12)).as_matrix()


def matrix_to_wxyz(R: np.ndarray) -> np.ndarray:
    """The unit quaternion ``(w, x, y, z)`` (w >= 0) of a rotation matrix [3,3]."""
    q = np.asarray(SO3.from_matrix(np.asarray(R, dtype=np.float64)).wxyz, dtype=np.float64)
    return -q if q[0] < 0 else q


def from_viser(wxyz: np.ndarray, position: np.ndarray, fov: float, aspect: float) -> ViewCamera:
    """A browser camera (viser's ``wxyz``, ``position``, vertical ``fov`` in radians, ``aspect``) as a
    :class:`ViewCamera`; the field of view is clamped to :data:`FOV_RANGE`."""
    c2w = np.concatenate([wxyz_to_matrix(wxyz), np.asarray(position, dtype=np.float64).reshape(3, 1)], 1)
    lo, hi = FOV_RANGE
    aspect = float(aspect) if np.isfinite(aspect) and aspect > 0 else 1.0
    return ViewCamera(c2w, float(min(max(fov, lo), hi)), aspect)


def to_viser(camera: ViewCamera) -> tuple[np.ndarray, np.ndarray]:
    """``(wxyz, position)`` that puts a browser camera at ``camera``."""
    return matrix_to_wxyz(camera.c2w[:3, :3]), camera.c2w[:3, 3].copy()


def capture_camera(cams: CaptureCameras, i: int) -> ViewCamera:
    """View ``i`` of the capture in its world frame, with its own vertical field of view and aspect."""
    c2w = cams.to_world(cams.c2w[i:i + 1, :3, :4])[0]
    fy = float(cams.K[i][1, 1])
    return ViewCamera(c2w, 2.0 * math.atan(0.5 * cams.height / fy), cams.width / cams.height)


def render_path(camera: ViewCamera, cams: CaptureCameras, long_side: int, name: str = "viewer") -> RenderPath:
    """The one-camera :class:`RenderPath` (normalized frame) that renders ``camera`` with the long side at
    ``long_side`` pixels."""
    return path_of([camera], cams, long_side, name)


def path_of(cameras: Sequence[ViewCamera], cams: CaptureCameras, long_side: int, name: str) -> RenderPath:
    """The :class:`RenderPath` (normalized frame) of world-frame ``cameras`` at ``long_side`` pixels (the first
    camera's aspect)."""
    H, W = cameras[0].size(long_side)
    c2w = cams.from_world(np.stack([c.c2w for c in cameras]))
    K = np.stack([c.intrinsics(H, W) for c in cameras])
    return RenderPath(name, torch.as_tensor(c2w, dtype=torch.float32), torch.as_tensor(K, dtype=torch.float32), H, W)


def scene_scale(cams: CaptureCameras) -> float:
    """A length that suits the capture in its world frame: the mean distance of its cameras from their
    centroid (world units), for frustum sizes and keyframe markers."""
    centres = cams.to_world(cams.c2w[:, :3, :4])[:, :3, 3]
    d = np.linalg.norm(centres - centres.mean(0), axis=1)
    return float(d.mean()) if d.size and d.mean() > 0 else 1.0
