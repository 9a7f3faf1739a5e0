"""Scene normalization (region of interest -> unit sphere) and capture-type detection.

All functions work on numpy float64 arrays; cameras are OpenCV ``c2w`` [N,3,4]
(z axis = viewing direction). A similarity ``T`` [4,4] maps original world
points to the normalized frame: ``x_norm = T @ x_orig`` (homogeneous).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

#: Cameras whose viewing axes all lie within this angle (degrees) of their mean
#: direction are considered a forward-facing (LLFF-style) capture.
FORWARD_FACING_MAX_ANGLE_DEG = 60.0


def look_at_centre(c2w: np.ndarray) -> np.ndarray:
    """Least-squares point closest to all optical axes (the common look-at point).

    Args:
        c2w: [N,3,4] OpenCV camera-to-world.

    Returns:
        [3] point; for (near-)parallel axes (forward-facing) the system is
        ill-conditioned and the mean camera centre is returned instead.
    """
    c = c2w[:, :3, 3]
    d = c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=-1, keepdims=True)
    A = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # projectors orthogonal to d
    lhs = A.sum(0)
    rhs = (A @ c[:, :, None]).sum(0)[:, 0]
    if np.linalg.cond(lhs) > 1e4:
        return c.mean(0)
    return np.linalg.solve(lhs, rhs)


def similarity(scale: float, centre: np.ndarray, rotation: Optional[np.ndarray] = None) -> np.ndarray:
    """4x4 ``T`` with ``T @ x = scale * R @ (x - centre)``."""
    R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = scale * R
    T[:3, 3] = -scale * R @ np.asarray(centre, dtype=np.float64)
    return T


def apply_similarity(T: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Express cameras ``c2w`` [N,3,4] in the frame ``x' = T x``; rotations stay orthonormal."""
    s = np.cbrt(np.linalg.det(T[:3, :3]))
    R = T[:3, :3] / s
    out = np.empty_like(c2w, dtype=np.float64)
    out[:, :3, :3] = R[None] @ c2w[:, :3, :3]
    out[:, :3, 3] = c2w[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    return out


def unit_sphere_from_cameras(
    c2w: np.ndarray, near: Optional[np.ndarray] = None, margin: float = 1.1
) -> np.ndarray:
    """Similarity putting the region the cameras look at inside the unit sphere.

    The centre is :func:`look_at_centre`; the radius is the median over cameras of
    ``distance_to_centre - near`` (how far the closest surface is from the centre)
    when ``near`` bounds are given, else half the median camera distance; it is
    clamped to [0.2, 0.9] x the median camera distance and multiplied by ``margin``.

    Returns:
        T [4,4].
    """
    centre = look_at_centre(c2w)
    dist = np.linalg.norm(c2w[:, :3, 3] - centre, axis=-1)
    med = float(np.median(dist))
    if near is not None:
        r = float(np.median(dist - np.asarray(near)))
    else:
        r = 0.5 * med
    r = float(np.clip(r, 0.2 * med, 0.9 * med)) * margin
    return similarity(1.0 / max(r, 1e-8), centre)


def unit_sphere_from_points(
    points: np.ndarray, c2w: np.ndarray, quantile: float = 0.75, margin: float = 1.1
) -> np.ndarray:
    """Similarity putting the bulk of a sparse point cloud inside the unit sphere.

    The centre is the cameras' look-at point when their axes converge (inward
    captures) else the median of the points; the radius is the ``quantile`` of the
    point distances to the centre (robust to far background points), capped at
    0.9 x the median camera distance so cameras stay outside, times ``margin``.

    Args:
        points: [P,3] sparse points in the original frame (P may be 0).
        c2w: [N,3,4] cameras in the original frame.

    Returns:
        T [4,4].
    """
    if points is None or len(points) < 10:
        return unit_sphere_from_cameras(c2w, margin=margin)
    capture, _ = detect_capture(c2w, None)
    centre = look_at_centre(c2w) if capture != "forward_facing" else np.median(points, axis=0)
    r = float(np.quantile(np.linalg.norm(points - centre, axis=-1), quantile))
    med_cam = float(np.median(np.linalg.norm(c2w[:, :3, 3] - centre, axis=-1)))
    if capture != "forward_facing":
        r = min(r, 0.9 * med_cam)
    r = max(r, 1e-8) * margin
    return similarity(1.0 / r, centre)


def detect_capture(c2w: np.ndarray, masks: Optional[object]) -> tuple[str, str]:
    """Classify a capture as ``"object"``, ``"forward_facing"`` or ``"unbounded"``.

    Rules: masks present -> ``"object"`` (the foreground is what is modelled);
    otherwise, if every camera's viewing axis lies within
    :data:`FORWARD_FACING_MAX_ANGLE_DEG` of the mean viewing direction ->
    ``"forward_facing"`` (LLFF-style, render in NDC); else ``"unbounded"``
    (inward-facing around an object, with background).

    Returns:
        (capture, human-readable reason).
    """
    if masks is not None:
        return "object", "foreground masks are available"
    z = np.asarray(c2w, dtype=np.float64)[:, :3, 2]
    z = z / np.linalg.norm(z, axis=-1, keepdims=True)
    mean = z.mean(0)
    if np.linalg.norm(mean) < 1e-6:
        return "unbounded", "viewing directions cancel out (cameras all around)"
    mean /= np.linalg.norm(mean)
    ang = np.degrees(np.arccos(np.clip(z @ mean, -1.0, 1.0)))
    if ang.max() < FORWARD_FACING_MAX_ANGLE_DEG:
        return "forward_facing", (
            f"all viewing axes within {ang.max():.1f} deg of the mean direction "
            f"(< {FORWARD_FACING_MAX_ANGLE_DEG:.0f})"
        )
    return "unbounded", (
        f"viewing axes spread up to {ang.max():.1f} deg from the mean direction "
        f"(>= {FORWARD_FACING_MAX_ANGLE_DEG:.0f}): inward-facing capture"
    )


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising ``sum |dst - (s R src + t)|^2`` (Umeyama 1991).

    Args:
        src, dst: [N,3] corresponding points.
    """
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var_s = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / max(var_s, 1e-12))
    t = mu_d - s * R @ mu_s
    return s, R, t


def near_far(capture: str, c2w: np.ndarray, bounds: Optional[np.ndarray] = None,
             T: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
    """The one near/far policy of the loaders: per-view ray ranges [N] in normalized units.

    * objects (and any capture without depth bounds): the unit sphere around each camera,
      ``near = max(|c| - 1, 0.05)``, ``far = |c| + 1`` (``c2w`` [N,3|4,4] already normalized);
    * forward-facing: the depth ``bounds`` [N,2] (file units) scaled by ``T``'s scale, exactly
      (NDC rendering uses near = 0, far = 1 anyway);
    * unbounded with bounds: those, 10% wider (``far`` at least 1% beyond ``near``).
    """
    if capture == "object" or bounds is None:
        dist = np.linalg.norm(c2w[:, :3, 3], axis=-1)
        return np.maximum(dist - 1.0, 0.05), dist + 1.0
    s = float(np.cbrt(np.linalg.det(T[:3, :3]))) if T is not None else 1.0
    near, far = bounds[:, 0] * s, bounds[:, 1] * s
    if capture == "forward_facing":
        return near, far
    near = np.maximum(near * 0.9, 1e-3)
    return near, np.maximum(far * 1.1, near * 1.01)
