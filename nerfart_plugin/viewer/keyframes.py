"""A camera path from keyframes: what the viewer's path editor saves as a nerfstudio ``camera_path.json``.

Positions follow a Catmull-Rom spline through the keyframes (uniform in keyframe index, the ends
extended by reflection), rotations a spherical linear interpolation between neighbouring keyframes, the field of
view a linear one; ``frames`` cameras are spread evenly over the keyframe intervals. The cameras are
in the capture's world frame, as the viewer shows them and as ``stage=render`` reads the file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from nerfart_plugin.cameras.capture import CaptureCameras
from nerfart_plugin.cameras.path import RenderPath, write_camera_path
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.viewer.cameras import ViewCamera, path_of

#: frames a path may have
FRAMES_RANGE = (2, 10_000)


def interpolate(keyframes: Sequence[ViewCamera], frames: int) -> list[ViewCamera]:
    """``frames`` cameras along the keyframes (see the module docstring); the first and the last are the
    first and the last keyframe. One keyframe: it, repeated. The aspect is the first keyframe's."""
    if not keyframes:
        raise ConfigError("the camera path has no keyframes: add at least two with 'Add keyframe'.")
    lo, hi = FRAMES_RANGE
    if not lo <= int(frames) <= hi:
        raise ConfigError(f"frames={frames}: a path has {lo} to {hi} frames.")
    if len(keyframes) == 1:
        return [keyframes[0]] * int(frames)
    n = len(keyframes)
    pos = np.stack([k.c2w[:, 3] for k in keyframes])
    rots = Rotation.from_matrix(np.stack([k.c2w[:, :3] for k in keyframes]))
    fovs = np.array([k.fov_y for k in keyframes])
    u = np.linspace(0.0, n - 1.0, int(frames))
    slerp = Slerp(np.arange(n, dtype=np.float64), rots)
    R = slerp(u).as_matrix()
    P = catmull_rom(pos, u)
    F = np.interp(u, np.arange(n), fovs)
    return [ViewCamera(np.concatenate([R[i], P[i][:, None]], 1), float(F[i]), keyframes[0].aspect)
            for i in range(len(u))]


def catmull_rom(points: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Points [N,D] of the uniform Catmull-Rom spline through ``points`` [N,D] at parameters ``u`` in
    [0, N-1]; the end points are extended by reflection, so evenly spaced points on a line give an even line."""
    pts = np.concatenate([2 * points[:1] - points[1:2], points, 2 * points[-1:] - points[-2:-1]])
    i = np.clip(np.floor(u).astype(int), 0, len(points) - 2)
    t = (u - i)[:, None]
    p0, p1, p2, p3 = pts[i], pts[i + 1], pts[i + 2], pts[i + 3]
    return 0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t ** 2
                  + (-p0 + 3 * p1 - 3 * p2 + p3) * t ** 3)


def save_path(keyframes: Sequence[ViewCamera], cams: CaptureCameras, out: Path, frames: int, fps: int,
              long_side: int) -> tuple[Path, RenderPath]:
    """Write the path through ``keyframes`` as a nerfstudio ``camera_path.json`` at ``out`` (world frame)
    and return it with its :class:`RenderPath`."""
    rp = path_of(interpolate(keyframes, frames), cams, long_side, Path(out).stem)
    rp.fps = int(fps)
    return write_camera_path(rp, cams, Path(out), int(fps)), rp
