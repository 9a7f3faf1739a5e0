"""Smooth camera paths for videos, and intrinsics rescaling.

* Object / unbounded scenes: an orbit around the cameras' look-at centre at the
  mean camera distance and elevation, sweeping the range of training azimuths
  (a full turn when the training views go all around, else a smooth back-and-forth
  sweep that loops seamlessly).
* Forward-facing scenes: LLFF's ``render_path_spiral``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Union

import numpy as np
import torch

from nerfart_plugin.cameras.capture import CaptureCameras, _np
from nerfart_plugin.data.normalize import look_at_centre

if TYPE_CHECKING:  # pragma: no cover
    from nerfart_plugin.data.scene import Scene


def _look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """OpenCV c2w [3,4] at ``eye`` looking at ``target`` with image-up roughly ``up``."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)  # OpenCV: right = down x forward = forward x up
    if np.linalg.norm(x) < 1e-8:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z, eye], 1)


def _orbit(c2w: np.ndarray, n_frames: int) -> np.ndarray:
    centre = look_at_centre(c2w)
    up = -c2w[:, :3, 1].mean(0)
    up = up / np.linalg.norm(up)
    rel = c2w[:, :3, 3] - centre
    dist = np.linalg.norm(rel, axis=-1)
    radius = float(dist.mean())
    elev = float(np.mean(np.arcsin(np.clip(rel @ up / dist, -1, 1))))
    # orthonormal basis (e1, e2) of the plane perpendicular to up
    e1 = rel.mean(0) - (rel.mean(0) @ up) * up
    if np.linalg.norm(e1) < 1e-6 * radius:
        e1 = rel[0] - (rel[0] @ up) * up
    e1 = e1 / np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    az = np.arctan2(rel @ e2, rel @ e1)  # relative to the mean direction
    order = np.sort(az)
    gaps = np.diff(np.concatenate([order, order[:1] + 2 * np.pi]))
    k = int(np.argmax(gaps))
    if gaps[k] < np.pi / 2:  # views all around: full turn
        az_path = order[(k + 1) % len(order)] + np.linspace(0, 2 * np.pi, n_frames, endpoint=False)
    else:  # sweep over the covered arc and back, smoothly (sinusoid)
        start = order[(k + 1) % len(order)]
        span = 2 * np.pi - gaps[k]
        mid, half = start + span / 2, span / 2
        az_path = mid + half * np.sin(np.linspace(0, 2 * np.pi, n_frames, endpoint=False))
    out = []
    for a in az_path:
        horiz = np.cos(a) * e1 + np.sin(a) * e2
        eye = centre + radius * (np.cos(elev) * horiz + np.sin(elev) * up)
        out.append(_look_at(eye, centre, up))
    return np.stack(out)


def _spiral(c2w: np.ndarray, near: np.ndarray, far: np.ndarray, n_frames: int, n_rots: int = 2,
            zrate: float = 0.5) -> np.ndarray:
    """LLFF ``render_path_spiral`` (computed in LLFF axes, returned as OpenCV)."""
    gl = c2w[:, :3, :4].copy()
    gl[:, :, 1:3] *= -1  # OpenCV -> OpenGL columns (right, up, back)
    centre = gl[:, :, 3].mean(0)
    back = gl[:, :, 2].sum(0)
    back /= np.linalg.norm(back)
    up = gl[:, :, 1].sum(0)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    avg = np.stack([right, up, back, centre], 1)
    close_depth, inf_depth = float(near.min()) * 0.9, float(far.max()) * 5.0
    dt = 0.75
    focal = 1.0 / ((1.0 - dt) / close_depth + dt / inf_depth)
    # LLFF: 90th percentile of |camera offsets| expressed in the average camera's axes
    rads = np.percentile(np.abs((gl[:, :, 3] - centre) @ avg[:, :3]), 90, axis=0)
    out = []
    for theta in np.linspace(0.0, 2 * np.pi * n_rots, n_frames + 1)[:-1]:
        c = avg[:, :3] @ (np.array([np.cos(theta), -np.sin(theta), -np.sin(theta * zrate)]) * rads) + centre
        target = avg[:, :3] @ np.array([0, 0, -focal]) + centre
        out.append(_look_at(c, target, up))
    return np.stack(out)


def orbit_path(scene: Union["Scene", "CaptureCameras"], n_frames: int = 120, kind: str = "auto") -> torch.Tensor:
    """A smooth, looping camera path for rendering a video of ``scene`` (a Scene or its
    :class:`CaptureCameras`): ``kind`` "orbit", "spiral" or "auto" (spiral for forward-facing
    captures, else orbit).

    Returns:
        c2w [F,3,4] float32, OpenCV, in the scene's normalized frame. Use the
        intrinsics of any training view (``scene.K[0]``) with it.
    """
    c2w = _np(scene.c2w)
    if kind == "spiral" or (kind == "auto" and scene.capture == "forward_facing"):
        path = _spiral(c2w, _np(scene.near), _np(scene.far), n_frames)
    else:
        path = _orbit(c2w, n_frames)
    return torch.from_numpy(path).float()
