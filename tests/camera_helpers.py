"""Synthetic cameras and images for the undistortion tests (COLMAP and nerfstudio)."""

from __future__ import annotations

import numpy as np


def pattern(xy: np.ndarray) -> np.ndarray:
    """Smooth RGB in [0.1, 0.9] as a function of the normalized ray (x, y) = (X/Z, Y/Z)."""
    x, y = xy[..., 0], xy[..., 1]
    return np.stack([0.5 + 0.4 * np.sin(3 * x + 1) * np.cos(2 * y), 0.5 + 0.4 * np.cos(2.5 * y - 0.5),
                     0.5 + 0.4 * np.sin(2 * x - 3 * y)], -1)


def pattern_seen_by(cam, width: int, height: int) -> np.ndarray:
    """uint8 [H,W,3]: the pattern (fixed to the camera frame) imaged through a ``pycolmap.Camera``'s lens."""
    v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    rays = np.asarray(cam.cam_from_img(np.stack([u, v], -1).reshape(-1, 2))).reshape(height, width, 2)
    return (np.clip(np.nan_to_num(pattern(rays)), 0, 1) * 255 + 0.5).astype(np.uint8)


def pinhole_pattern(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """float [H,W,3]: what an undistorted pinhole image with intrinsics K must show."""
    v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    return pattern(np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]], -1))


def interior_error(img: np.ndarray, expected: np.ndarray, border: int = 2) -> tuple[float, np.ndarray]:
    """Mean |img - expected| over pixels that sample inside the source (non-black), away from the border."""
    inside = (img > 0).any(-1)
    inside[:border], inside[-border:], inside[:, :border], inside[:, -border:] = False, False, False, False
    return float(np.abs(img - expected)[inside].mean()), inside


def look_at(centre: np.ndarray, up: tuple = (0.0, 0.0, -1.0)) -> np.ndarray:
    """OpenCV c2w [4,4] at ``centre`` looking at the origin; image y points along -``up``."""
    z = -centre / np.linalg.norm(centre)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    M = np.eye(4)
    M[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    M[:3, 3] = centre
    return M
