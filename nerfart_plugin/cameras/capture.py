"""A capture's cameras without its photos (:class:`CaptureCameras`: what a finished run needs to render new
views, written as ``cameras.json``), their frames (world <-> normalized) and intrinsics rescaling."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Union

import numpy as np
import torch

from nerfart_plugin.data.normalize import look_at_centre

if TYPE_CHECKING:  # pragma: no cover
    from nerfart_plugin.data.scene import Scene


def scale_intrinsics(K: torch.Tensor, sx: float, sy: Union[float, None] = None) -> torch.Tensor:
    """Intrinsics [...,3,3] for an image resized by (sx, sy) = (W'/W, H'/H).

    Exact under the pixel-centre convention (centre of pixel u at u + 0.5): the
    first row scales by ``sx``, the second by ``sy``.
    """
    sy = sx if sy is None else sy
    K = K.clone()
    K[..., 0, :] = K[..., 0, :] * sx
    K[..., 1, :] = K[..., 1, :] * sy
    return K


def _np(x: Any) -> np.ndarray:
    return x.detach().cpu().double().numpy() if torch.is_tensor(x) else np.asarray(x, dtype=np.float64)


def ndc_to_normalized(points: np.ndarray, fx: float, fy: float, W: float, H: float,
                      near_plane: float = 1.0, max_ndc_z: float = 0.999) -> tuple[np.ndarray, np.ndarray]:
    """Invert NeRF's NDC warp (:func:`nerfart_plugin.data.rays.ndc_rays`): NDC points [N,3] -> the
    normalized frame (the average camera at the origin looking along -z). Points with
    ``z_ndc >= max_ndc_z`` lie at (near) infinity; returns ``(points [N,3], finite [N] bool)``."""
    p = np.asarray(points, dtype=np.float64)
    finite = p[:, 2] < max_ndc_z
    z = 2.0 * near_plane / (np.minimum(p[:, 2], max_ndc_z) - 1.0)
    x = -p[:, 0] * z * W / (2.0 * fx)
    y = -p[:, 1] * z * H / (2.0 * fy)
    return np.stack([x, y, z], -1), finite


@dataclass
class CaptureCameras:
    """A capture's cameras as a finished run needs them to render new views, without the photos.

    Attributes:
        c2w: [N,3,4] OpenCV camera-to-world in the normalized (training) frame.
        K: [N,3,3] intrinsics at ``width`` x ``height`` pixels.
        near / far: [N] ray bounds (normalized scene units).
        capture: "object" | "unbounded" | "forward_facing"; ndc: rays are NDC-warped.
        normalization: [4,4] T of x_norm = T x_world (the capture's world frame -> training frame).
        train_ids: the training views; names: the image names.
    """

    c2w: np.ndarray
    K: np.ndarray
    width: int
    height: int
    near: np.ndarray
    far: np.ndarray
    capture: str
    ndc: bool
    normalization: np.ndarray
    train_ids: list[int] = field(default_factory=list)
    names: list[str] = field(default_factory=list)

    @classmethod
    def from_scene(cls, scene: "Scene", ndc: bool) -> "CaptureCameras":
        return cls(_np(scene.c2w)[:, :3, :4], _np(scene.K), int(scene.width), int(scene.height), _np(scene.near),
                   _np(scene.far), scene.capture, bool(ndc), _np(scene.normalization), list(scene.train_ids),
                   list(scene.image_names))

    @classmethod
    def from_json(cls, d: dict) -> "CaptureCameras":
        """Read back a run's ``cameras.json`` (:func:`viewer_cameras`, in either frame)."""
        T = np.asarray(d["normalization"], dtype=np.float64)
        c2w = np.asarray(d["c2w"], dtype=np.float64)
        if d.get("frame") == "world":
            c2w = similarity_c2w(T, c2w)
        n = len(c2w)
        dist = np.linalg.norm(c2w[:, :3, 3], axis=-1)  # without bounds: the unit sphere's, seen from each camera
        near = np.asarray(d["near"], dtype=np.float64) if "near" in d else np.maximum(dist - 1.0, 0.01)
        far = np.asarray(d["far"], dtype=np.float64) if "far" in d else dist + 1.0
        return cls(c2w, np.asarray(d["K"], dtype=np.float64), int(d["width"]), int(d["height"]), near, far,
                   d.get("capture", "object"),
                   bool(d.get("ndc", False)), T, list(d.get("train_ids", range(n))), list(d.get("names", [])))

    def field_to_world(self, points: np.ndarray) -> np.ndarray:
        """Points [N,3] of the field's frame (normalized; NDC for forward-facing captures, points at infinity
        clipped to the far plane) -> the capture's world frame [N,3]."""
        p = np.asarray(points, dtype=np.float64)
        if self.ndc:
            K = np.asarray(self.K[0], dtype=np.float64)
            p, _ = ndc_to_normalized(p, float(K[0, 0]), float(K[1, 1]), float(self.width), float(self.height))
        T = np.linalg.inv(np.asarray(self.normalization, dtype=np.float64))
        return p @ T[:3, :3].T + T[:3, 3]

    def to_world(self, c2w: np.ndarray) -> np.ndarray:
        """Cameras [F,3,4] of the normalized frame in the capture's world frame."""
        return similarity_c2w(np.linalg.inv(self.normalization), np.asarray(c2w, dtype=np.float64))

    def from_world(self, c2w: np.ndarray) -> np.ndarray:
        """Cameras [F,3,4] of the capture's world frame in the normalized frame."""
        return similarity_c2w(self.normalization, np.asarray(c2w, dtype=np.float64))


def front_camera(c2w: np.ndarray) -> int:
    """Index of the capture's front view in ``c2w`` [N,3,4|4,4] (OpenCV): the camera nearest in
    azimuth (around the cameras' up vector) to their mean direction from the look-at centre, when
    the cameras have one (resultant length > 0.3, e.g. a selfie sweep); else camera 0, the
    capture's first view (an all-around capture has no preferred side)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    centre = look_at_centre(c2w)
    up = -c2w[:, :3, 1].mean(0)
    up = up / max(np.linalg.norm(up), 1e-12)
    rel = c2w[:, :3, 3] - centre
    horiz = rel - (rel @ up)[:, None] * up
    unit = horiz / np.maximum(np.linalg.norm(horiz, axis=1, keepdims=True), 1e-12)
    mean = unit.mean(0)
    if np.linalg.norm(mean) <= 0.3:
        return 0
    return int(np.argmax(unit @ (mean / np.linalg.norm(mean))))


def viewer_cameras(scene: "Scene", frame: str = "normalized", ndc: bool = False) -> dict:
    """What a mesh viewer (and ``stage=render``) needs to open on the capture's own view, as plain data
    (JSON-ready): every camera (``c2w`` [N,3,4] OpenCV, ``K``, image size, names, ``near`` / ``far`` in
    normalized units, ``train_ids``) in ``frame`` (that of the exported meshes: "normalized", as trained,
    or "world", the capture's own), the look-at ``centre``, the ``up`` vector, the ``front`` camera
    index (:func:`front_camera`), ``ndc`` and the ``normalization`` T (x_norm = T x_world);
    :meth:`CaptureCameras.from_json` reads it back."""
    c2w = _np(scene.c2w)[:, :3, :4]
    if frame == "world":
        c2w = similarity_c2w(np.linalg.inv(_np(scene.normalization)), c2w)
    up = -c2w[:, :3, 1].mean(0)
    return {"frame": frame, "c2w": c2w.tolist(), "K": _np(scene.K).tolist(),
            "width": int(scene.width), "height": int(scene.height), "names": list(scene.image_names),
            "centre": look_at_centre(c2w).tolist(), "up": (up / max(np.linalg.norm(up), 1e-12)).tolist(),
            "front": front_camera(c2w), "capture": scene.capture, "ndc": bool(ndc),
            "near": _np(scene.near).tolist(), "far": _np(scene.far).tolist(),
            "train_ids": [int(i) for i in scene.train_ids],
            "normalization": _np(scene.normalization).tolist()}


def similarity_c2w(S: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Cameras [N,3,4] moved by the similarity S [4,4] (x' = S x): centres mapped, rotations rotated
    by S's rotation (its scale divided out, so the axes stay orthonormal)."""
    scale = np.cbrt(abs(np.linalg.det(S[:3, :3])))
    R = S[:3, :3] / scale
    out = np.empty_like(c2w)
    out[:, :3, :3] = R @ c2w[:, :3, :3]
    out[:, :3, 3] = c2w[:, :3, 3] @ S[:3, :3].T + S[:3, 3]
    return out
