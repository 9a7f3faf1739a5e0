"""The camera paths of ``stage=render``: orbit, spiral, the training cameras, or a nerfstudio
``camera_path.json``; and that file written back, so a path can be edited and rendered again.

nerfstudio's viewer (and ``ns-render``) use this layout, which is read and written here::

    {"camera_type": "perspective", "render_height": H, "render_width": W, "fps": 24, "seconds": 5.0,
     "camera_path": [{"camera_to_world": [16 numbers: a 4x4 matrix, row-major, OpenGL axes],
                      "fov": 50.0,            # vertical field of view, degrees
                      "aspect": 1.777}, ...]}

Files this project writes add each camera's exact ``intrinsics`` (3x3 at the render size, row-major;
nerfstudio ignores the key), so a path written and read back renders the same pixels; without it
the pixels are square and the principal point centred, as in nerfstudio.

OpenGL camera axes (x right, y up, looking down -z) are converted to the project's OpenCV ones
(x right, y down, looking down +z). The cameras are in the capture's world frame (that of the
exported meshes and ``cameras.json``) or, with ``render.path_frame=normalized``, in the training
frame. A path made in nerfstudio's own viewer is in nerfstudio's normalized frame (its
``dataparser_transforms.json``), which is neither: export it from the capture's frame instead.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from nerfart_plugin.cameras.capture import CaptureCameras, scale_intrinsics
from nerfart_plugin.cameras.orbits import orbit_path
from nerfart_plugin.config.schema import RenderConfig
from nerfart_plugin.config.validate import section
from nerfart_plugin.errors import ConfigError, DataError
from nerfart_plugin.utils.io import atomic_write_json

#: the named paths of ``render.path`` (anything else is a camera_path.json file)
NAMED_PATHS = ("orbit", "spiral", "training")
_GL = np.diag([1.0, -1.0, -1.0])  # OpenCV <-> OpenGL camera axes (an involution)


@dataclass
class RenderPath:
    """Cameras to render, in the normalized (training) frame.

    Attributes:
        name: what the path is (``orbit``, ``training``, a file's stem), for output folder names.
        c2w: [F,3,4] OpenCV camera-to-world; K: [F,3,3] intrinsics at ``width`` x ``height`` pixels.
        fps: frames per second the path asks for (a file's), None: the caller's choice.
    """

    name: str
    c2w: torch.Tensor
    K: torch.Tensor
    height: int
    width: int
    fps: Optional[int] = None

    def __len__(self) -> int:
        return int(self.c2w.shape[0])


def frame_size(cams: CaptureCameras, long_side: Optional[int]) -> tuple[int, int]:
    """(H, W) of the capture's images with the long side at ``long_side`` pixels (None: as captured)."""
    if long_side is None:
        return cams.height, cams.width
    s = long_side / max(cams.height, cams.width)
    return max(1, round(cams.height * s)), max(1, round(cams.width * s))


def scaled_K(cams: CaptureCameras, ids: list[int], H: int, W: int) -> torch.Tensor:
    """[len(ids),3,3] intrinsics of views ``ids`` for images resized to H x W."""
    return scale_intrinsics(torch.as_tensor(cams.K[ids], dtype=torch.float32), W / cams.width, H / cams.height)


def resolve_path(cams: CaptureCameras, spec: str, frames: int = 120, long_side: Optional[int] = None,
                 path_frame: str = "world") -> RenderPath:
    """The cameras of ``render.path`` = ``spec``: orbit / spiral (``frames`` cameras, a training view's
    intrinsics), training (the training cameras in capture order) or a camera_path.json file (its cameras
    in ``path_frame``). ``long_side``: frame size in pixels (None: the capture's; a file: its own size)."""
    if spec in ("orbit", "spiral"):
        H, W = frame_size(cams, long_side)
        c2w = orbit_path(cams, frames, kind=spec)
        ref = cams.train_ids[:1] or [0]
        return RenderPath(spec, c2w, scaled_K(cams, ref, H, W).expand(len(c2w), 3, 3).clone(), H, W)
    if spec == "training":
        ids = list(cams.train_ids) or list(range(len(cams.c2w)))
        H, W = frame_size(cams, long_side)
        return RenderPath("training", torch.as_tensor(cams.c2w[ids], dtype=torch.float32), scaled_K(cams, ids, H, W), H, W)
    path = Path(spec).expanduser()
    if not path.is_file():
        raise ConfigError(f"render.path={spec}: not one of {', '.join(NAMED_PATHS)} and no such file; give a path "
                          "name or a nerfstudio camera_path.json (stage=render writes one beside each video).")
    return read_camera_path(path, cams, path_frame, long_side)


def read_camera_path(path: Path, cams: CaptureCameras, frame: str = "world",
                     long_side: Optional[int] = None) -> RenderPath:
    """A nerfstudio ``camera_path.json`` (see the module doc) as a :class:`RenderPath` in the normalized frame;
    ``long_side`` resizes its ``render_width`` x ``render_height`` (the field of view is kept)."""
    try:
        d = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"Cannot read the camera path {path}: {exc}. Give a JSON file as nerfstudio's viewer "
                        "exports it (keys render_height, render_width, camera_path).") from exc
    kind = d.get("camera_type", "perspective")
    if kind != "perspective":
        raise DataError(f"{path}: camera_type {kind!r} is not supported; export the path with a perspective camera.")
    entries = d.get("camera_path")
    if not isinstance(entries, list) or not entries:
        raise DataError(f"{path}: no 'camera_path' list of cameras; export the path from nerfstudio's viewer "
                        "(Render -> Generate command) or write it with stage=render.")
    try:
        H0, W0 = int(d["render_height"]), int(d["render_width"])
        gl = np.asarray([np.asarray(e["camera_to_world"], dtype=np.float64).reshape(4, 4) for e in entries])
        fov = np.asarray([float(e["fov"]) for e in entries])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{path}: every camera needs 'camera_to_world' (16 numbers) and 'fov' (degrees), and the "
                        f"file render_height / render_width ({exc!r}).") from exc
    if not np.all(np.isfinite(gl)) or np.any((fov <= 0) | (fov >= 180)):
        raise DataError(f"{path}: camera matrices must be finite and fov in (0, 180) degrees.")
    c2w = gl[:, :3, :4].copy()
    c2w[:, :3, :3] = c2w[:, :3, :3] @ _GL
    if frame == "world":
        c2w = cams.from_world(c2w)
    s = 1.0 if long_side is None else long_side / max(H0, W0)
    H, W = max(1, round(H0 * s)), max(1, round(W0 * s))
    if all("intrinsics" in e for e in entries):  # written by this project: the exact K at H0 x W0
        K = np.asarray([np.asarray(e["intrinsics"], dtype=np.float64).reshape(3, 3) for e in entries])
        K[:, 0] *= W / W0
        K[:, 1] *= H / H0
    else:  # nerfstudio: square pixels, centred principal point
        fy = 0.5 * H / np.tan(np.deg2rad(fov) / 2)
        K = np.zeros((len(fov), 3, 3))
        K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = fy, fy, W / 2, H / 2, 1.0
    return RenderPath(Path(path).stem, torch.as_tensor(c2w, dtype=torch.float32), torch.as_tensor(K, dtype=torch.float32),
                      H, W, _file_fps(d.get("fps"), path))


def _file_fps(fps: Any, path: Path) -> Optional[int]:
    """A camera path file's ``fps``, checked as ``render.fps`` on the command line is (None: not given)."""
    if fps is None:
        return None
    try:
        value = int(round(float(fps)))
        section(RenderConfig, {"fps": value})
    except (TypeError, ValueError, ConfigError) as exc:
        raise DataError(f"{path}: its fps {fps!r} is refused, as render.fps={fps} would be ({exc}); set the file's "
                        "\"fps\" to a whole number of frames per second from 1 to 240.") from None
    return value


def write_camera_path(rp: RenderPath, cams: CaptureCameras, path: Path, fps: int, frame: str = "world") -> Path:
    """``rp`` as a nerfstudio ``camera_path.json`` (cameras in ``frame``; ``fov`` from each K's fy, and the
    exact K as ``intrinsics``, which nerfstudio ignores and :func:`read_camera_path` prefers), to edit and
    render again with ``render.path=<file>``."""
    c2w = rp.c2w.detach().cpu().double().numpy()
    if frame == "world":
        c2w = cams.to_world(c2w)
    Ks = rp.K.detach().cpu().double().numpy()
    cameras = []
    for m, K in zip(c2w, Ks):
        gl = np.eye(4)
        gl[:3, :3], gl[:3, 3] = m[:, :3] @ _GL, m[:, 3]
        cameras.append({"camera_to_world": gl.reshape(-1).tolist(),
                        "fov": float(np.rad2deg(2 * math.atan(0.5 * rp.height / float(K[1, 1])))),
                        "aspect": rp.width / rp.height, "intrinsics": K.reshape(-1).tolist()})
    atomic_write_json(Path(path), {"camera_type": "perspective", "render_height": rp.height, "render_width": rp.width,
                                   "fps": fps, "seconds": len(rp) / fps, "frame": frame, "camera_path": cameras})
    return Path(path)
