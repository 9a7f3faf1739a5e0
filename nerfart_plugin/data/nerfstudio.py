"""nerfstudio / instant-ngp / Blender ``transforms.json`` scenes (registry data "nerfstudio").

Layout::

    scene/
      transforms.json                     all frames (nerfstudio, instant-ngp), or Blender's
      transforms_train.json, transforms_val.json[, transforms_test.json]
      ...                                 images wherever the frames' file_path point
                                          (relative to the json's folder)

Keys (top level: defaults for every frame; a frame may override any camera key)::

    camera_angle_x [camera_angle_y]   horizontal [vertical] field of view in radians (Blender)
    fl_x fl_y cx cy w h               pinhole intrinsics in pixels of w x h images (fl_y
                                      defaults to fl_x, cx/cy to the image centre, w/h to
                                      the image size)
    camera_model                      OPENCV (default), PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL,
                                      RADIAL: perspective; OPENCV_FISHEYE: fisheye
    k1 k2 k3 k4 p1 p2                 perspective: OpenCV's (k1, k2, p1, p2, k3, k4) as
                                      nerfstudio hands them to cv2.undistort; fisheye:
                                      cv2.fisheye's k1..k4
    frames: [{file_path, transform_matrix, mask_path?}, ...]
      file_path                       the image, with or without extension (.png, .jpg, ...)
      transform_matrix                4x4 camera-to-world with OpenGL camera axes (x right,
                                      y up, z back); converted to OpenCV by flipping y and z
      mask_path                       optional foreground matte (white = object)
    train_filenames val_filenames test_filenames   optional split (nerfstudio)
    aabb | aabb_scale [scale offset]  optional scene box (below)

Images and masks: lens distortion is removed with OpenCV at the native size (the
pinhole K is kept; see :mod:`nerfart_plugin.data.undistort` for the half-pixel
convention), then images are resized (``data.resolution``, default ``auto``: long
side min(native, 480)). An RGBA image's alpha is the mask when the frames have no
``mask_path``: the scene keeps the straight colours (the background colour where
alpha is 0) and the datamodule composites ``rgb * alpha + background * (1 - alpha)``
exactly once; with ``use_masks=false`` (or ``mask_path`` masks) RGBA images are
composited on ``background`` here.

Scene box -> unit sphere of the normalized frame:

1. ``aabb`` ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` (the file's world frame):
   the box's circumscribed sphere becomes the unit sphere.
2. ``aabb_scale`` (instant-ngp): ngp maps positions to ``p * scale + offset``
   (defaults 0.33 and [0.5, 0.5, 0.5]) and bounds the scene by the cube of side
   ``aabb_scale`` centred on ngp's unit cube; the unit cube (``aabb_scale = 1``) is
   the foreground, so its circumscribed sphere becomes the unit sphere, and what lies
   out to ``aabb_scale`` is background (the environment map of unbounded captures).
3. otherwise the region the cameras look at, as for LLFF's unbounded captures
   (:func:`nerfart_plugin.data.normalize.unit_sphere_from_cameras`).

Capture type as for the other loaders: masks -> ``"object"``; else forward-facing
cameras -> ``"forward_facing"`` (LLFF normalization, NDC) when a box bounds the
depths, ``"unbounded"`` (with a note) without one; else ``"unbounded"``.
Splits: Blender's files (``data.splits``, default train + val: val/test frames are
``val_ids``), nerfstudio's ``*_filenames`` lists, else every ``holdout_every``-th view.
"""

from __future__ import annotations

import json
import os
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
from PIL import Image

from nerfart_plugin.config.components import configured
from nerfart_plugin.config.registry import register
from nerfart_plugin.config.types import HoldoutEvery, Setting
from nerfart_plugin.data.common import make_scene, require_dir
from nerfart_plugin.data.images import (IMAGE_EXTS, choose_resolution, image_size, read_image, read_rgba, resize_float,
    resize_premultiplied, target_size)
from nerfart_plugin.data.llff import forward_facing_normalization
from nerfart_plugin.data.loader import LoaderConfig, LoaderContext
from nerfart_plugin.data.normalize import apply_similarity, detect_capture, similarity, unit_sphere_from_cameras
from nerfart_plugin.data.scene import CaptureType, Scene
from nerfart_plugin.data.undistort import UndistortMaps, opencv_maps, remap
from nerfart_plugin.errors import ConfigError, DataError

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")
PERSPECTIVE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
FISHEYE_MODELS = ("OPENCV_FISHEYE",)
DIST_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
#: OpenGL camera axes (x right, y up, z back) -> OpenCV (x right, y down, z forward)
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
#: instant-ngp's defaults for ``scale`` and ``offset`` (``p_ngp = p * scale + offset``)
NGP_SCALE, NGP_OFFSET = 0.33, (0.5, 0.5, 0.5)
FORMAT_HINT = "see data/README.md (nerfstudio / instant-ngp transforms.json)"


@dataclass
class Camera:
    """Intrinsics of one frame: pixels of ``w`` x ``h`` images, pixel centres at +0.5.

    ``dist`` is OpenCV's vector (perspective: k1, k2, p1, p2[, k3[, k4, 0, 0]];
    fisheye: k1..k4).
    """

    w: int
    h: int
    fx: float
    fy: float
    cx: float
    cy: float
    model: str
    dist: tuple[float, ...]

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fisheye(self) -> bool:
        return self.model in FISHEYE_MODELS


@dataclass
class Frame:
    """One view: image (and optional matte) file, OpenCV c2w [4,4] in the file's frame, camera, split."""

    image: Path
    mask: Optional[Path]
    c2w: np.ndarray
    camera: Camera
    split: str


# --------------------------------------------------------------------------- reading the files
def find_transforms(root: Path, splits: Sequence[str]) -> list[tuple[str, Path]]:
    """(split, json) pairs: ``transforms.json`` (split "all"), else Blender's per-split files.

    Raises:
        DataError: no transforms file, or Blender files without ``transforms_train.json``.
    """
    if root.is_file():
        return [("all", root)]
    if (root / "transforms.json").is_file():
        return [("all", root / "transforms.json")]
    bad = [s for s in splits if s not in SPLITS]
    if bad:
        raise DataError(f"data.splits has {bad}: use a list of {', '.join(SPLITS)} (default [train, val]).")
    found = [(s, root / f"transforms_{s}.json") for s in splits if (root / f"transforms_{s}.json").is_file()]
    if not (root / "transforms_train.json").is_file():
        raise DataError(
            f"No transforms.json (nerfstudio / instant-ngp) or transforms_train.json (Blender) in {root}: point "
            "data.path at the folder holding it (or at the .json file itself); for COLMAP models use data=selfie, "
            "for cameras.npz data=h3ds."
        )
    return found


def read_transforms(path: Path) -> dict:
    """The parsed JSON object of a transforms file, with a non-empty ``frames`` list.

    Raises:
        DataError: unreadable or invalid JSON, not an object, no frames.
    """
    try:
        meta = json.loads(Path(path).read_text(encoding="utf-8"))
    except UnicodeDecodeError as e:
        raise DataError(f"Cannot read {path}: not UTF-8 text ({e.reason}); it must be a JSON file, "
                        f"{FORMAT_HINT}.") from e
    except json.JSONDecodeError as e:
        raise DataError(f"{path} is not valid JSON (line {e.lineno}, column {e.colno}: {e.msg}); fix the file, "
                        f"{FORMAT_HINT}.") from e
    except (OSError, RecursionError) as e:
        raise DataError(f"Cannot read {path} ({e.__class__.__name__}: {e}); {FORMAT_HINT}.") from e
    if not isinstance(meta, dict):
        raise DataError(f"{path} holds a JSON {type(meta).__name__}, expected an object with a 'frames' list; "
                        f"{FORMAT_HINT}.")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DataError(f"{path} has no 'frames' list (or it is empty): add one entry per image with file_path "
                        f"and transform_matrix; {FORMAT_HINT}.")
    return meta


def _number(d: dict, key: str, where: str, default: Any = None, positive: bool = False) -> Any:
    """``d[key]`` as a finite float (``default`` when absent or null)."""
    v = d.get(key)
    if v is None:
        return default
    try:
        ok = not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(float(v))
    except OverflowError:  # JSON integers have no size limit
        ok = False
    if not ok:
        raise DataError(f"{where}: {key}={str(v)[:40]} is not a finite number; fix it in the file.")
    if positive and float(v) <= 0:
        raise DataError(f"{where}: {key}={v!r} must be positive; fix it in the file.")
    return float(v)


def _size(d: dict, key: str, where: str) -> Optional[int]:
    v = _number(d, key, where, positive=True)
    if v is not None and (v != int(v) or v > 1e6):
        raise DataError(f"{where}: {key}={v!r} must be a whole number of pixels; fix it in the file.")
    return None if v is None else int(v)


def _distortion(get: Any, model: str, where: str, notes: list[str]) -> tuple[float, ...]:
    k1, k2, k3, k4, p1, p2 = (get(k) or 0.0 for k in DIST_KEYS)
    if model in FISHEYE_MODELS:
        if p1 or p2:
            notes.append(f"{where}: p1/p2 are not part of {model} (cv2.fisheye): ignored")
        return (k1, k2, k3, k4)
    if k4:
        return (k1, k2, p1, p2, k3, k4, 0.0, 0.0)
    return (k1, k2, p1, p2, k3)


def parse_camera(meta: dict, frame: dict, where: str, image: Path, notes: list[str]) -> Camera:
    """Intrinsics of ``frame`` (its keys over the file's), for the size of its ``image``.

    Intrinsics given for another size of the same aspect ratio (downscaled copies) are
    scaled to the image; a different aspect ratio is a DataError.
    """
    merged = {**meta, **frame}
    get = lambda k, **kw: _number(merged, k, where, **kw)  # noqa: E731
    model = merged.get("camera_model") or "OPENCV"
    if model not in PERSPECTIVE_MODELS + FISHEYE_MODELS:
        raise DataError(
            f"{where}: camera_model {model!r} is not supported (only pinhole-undistortable models: "
            f"{', '.join(PERSPECTIVE_MODELS + FISHEYE_MODELS)}); convert the capture to perspective images first."
        )
    W, H = image_size(image)
    w, h = _size(merged, "w", where) or W, _size(merged, "h", where) or H
    fx = get("fl_x", positive=True)
    if fx is None and (ax := get("camera_angle_x", positive=True)) is not None:
        fx = 0.5 * w / math.tan(0.5 * ax) if ax < math.pi else -1.0
    if fx is None or not (0 < fx < 1e8):
        raise DataError(f"{where}: no valid focal length: give fl_x (pixels) or camera_angle_x (radians, < pi); "
                        f"{FORMAT_HINT}.")
    fy = get("fl_y", positive=True)
    if fy is None and (ay := get("camera_angle_y", positive=True)) is not None and ay < math.pi:
        fy = 0.5 * h / math.tan(0.5 * ay)
    cam = Camera(w, h, fx, fy or fx, get("cx", default=w / 2.0), get("cy", default=h / 2.0), model,
                 _distortion(get, model, where, notes))
    return _fit_to_image(cam, W, H, where, image)


def _fit_to_image(cam: Camera, W: int, H: int, where: str, image: Path) -> Camera:
    if (cam.w, cam.h) == (W, H):
        return cam
    if abs(cam.w / cam.h - W / H) > 0.01 * W / H:
        raise DataError(f"{where}: intrinsics are for {cam.w}x{cam.h} images but {image} is {W}x{H} (another "
                        "aspect ratio): fix w/h (and fl_x, cx, ...) or use the images the file was made for.")
    sx, sy = W / cam.w, H / cam.h
    return Camera(W, H, cam.fx * sx, cam.fy * sy, cam.cx * sx, cam.cy * sy, cam.model, cam.dist)


def parse_pose(frame: dict, where: str) -> np.ndarray:
    """OpenCV c2w [4,4] from an OpenGL ``transform_matrix`` (4x4 or 3x4, orthonormal rotation)."""
    M = frame.get("transform_matrix")
    try:
        M = np.array(M, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        M = None
    if M is None or M.shape not in ((4, 4), (3, 4)) or not np.isfinite(M).all():
        raise DataError(f"{where}: transform_matrix must be a 4x4 (or 3x4) list of finite numbers (camera-to-"
                        f"world, OpenGL axes); {FORMAT_HINT}.")
    c2w = np.eye(4)
    c2w[:3] = M[:3]
    R = c2w[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-2 or np.linalg.det(R) < 0:
        raise DataError(f"{where}: the rotation of transform_matrix is not orthonormal and right-handed "
                        f"(camera-to-world without scale); fix the file.")
    return c2w @ GL_TO_CV


def resolve_image(base: Path, rel: Any, where: str, key: str = "file_path") -> Path:
    """The file ``rel`` names under ``base`` (a relative path may not climb out of it with ``..``; links and
    absolute paths are the user's own); without an extension the usual image ones are tried."""
    if not isinstance(rel, str) or not rel.strip():
        raise DataError(f"{where}: {key} is missing or not a string; give the image path relative to the json.")
    p = base / rel
    if not Path(rel).is_absolute() and not Path(os.path.normpath(p)).is_relative_to(os.path.normpath(base)):
        raise DataError(f"{where}: {key} {rel!r} leads outside the capture's folder {base}: the images and masks "
                        "must lie inside it (a path that leaves it is refused); move the files into the folder or fix "
                        "the path.")
    if p.is_file():
        return p
    tried = [p]
    if p.suffix.lower() not in IMAGE_EXTS:
        for ext in IMAGE_EXTS:
            q = p.with_name(p.name + ext)
            if q.is_file():
                return q
        tried.append(p.with_name(p.name + ".png|.jpg|..."))
    raise DataError(f"{where}: {key} {rel!r} not found (looked for {', '.join(str(t) for t in tried)}); "
                    "copy the image there or fix the path.")


def parse_frames(files: list[tuple[str, Path]], notes: list[str]) -> tuple[list[Frame], dict]:
    """All frames of the files, in file order, and the first file's top-level keys."""
    frames: list[Frame] = []
    first: Optional[dict] = None
    for split, path in files:
        meta = read_transforms(path)
        first = meta if first is None else first
        for i, fr in enumerate(meta["frames"]):
            where = f"{path} frames[{i}]"
            if not isinstance(fr, dict):
                raise DataError(f"{where} is a {type(fr).__name__}, expected an object with file_path and "
                                "transform_matrix.")
            image = resolve_image(path.parent, fr.get("file_path"), where)
            mask = resolve_image(path.parent, fr["mask_path"], where, "mask_path") if "mask_path" in fr else None
            frames.append(Frame(image, mask, parse_pose(fr, where), parse_camera(meta, fr, where, image, notes),
                                split))
    assert first is not None
    return frames, first


# --------------------------------------------------------------------------- splits and box
def file_split(frames: list[Frame], meta: dict, source: Path) -> Optional[tuple[list[int], list[int]]]:
    """(train, val) ids from Blender split files or nerfstudio's ``*_filenames`` lists, else None."""
    if any(f.split != "all" for f in frames):
        train = [i for i, f in enumerate(frames) if f.split == "train"]
        return train, [i for i, f in enumerate(frames) if f.split != "train"]
    lists = {s: meta.get(f"{s}_filenames") for s in SPLITS}
    if lists["train"] is None:
        return None
    index: dict[str, int] = {}
    for i, f in enumerate(frames):
        index.setdefault(_relative(f.image, source), i)
        index.setdefault(f.image.name, i)
    ids = {}
    for s, names in lists.items():
        if names is None:
            ids[s] = []
            continue
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise DataError(f"{source}: {s}_filenames must be a list of file paths; fix the file.")
        missing = [n for n in names if _norm(n) not in index and Path(n).name not in index]
        if missing:
            raise DataError(f"{source}: {s}_filenames names {missing[:3]}, which no frame's file_path loads; "
                            "fix the list (or remove it to hold out every 8th view).")
        ids[s] = [index.get(_norm(n), index.get(Path(n).name)) for n in names]
    return ids["train"], ids["val"] + ids["test"]


def _relative(p: Path, root: Path) -> str:
    """``p`` relative to the scene folder (POSIX), e.g. ``train/r_0.png``."""
    base = root.parent if root.is_file() else root
    try:
        return p.relative_to(base).as_posix()
    except ValueError:
        return p.name


def _norm(name: str) -> str:
    return str(Path(name.removeprefix("./")))


def scene_box(meta: dict, source: Path, notes: list[str]) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """The foreground box (min [3], max [3]) in the file's frame from ``aabb`` or ``aabb_scale``, or None."""
    where = str(source)
    if meta.get("aabb") is not None:
        try:
            box = np.array(meta["aabb"], dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            box = None
        if box is None or box.shape != (2, 3) or not np.isfinite(box).all() or (box[1] <= box[0]).any():
            raise DataError(f"{where}: aabb must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max; "
                            "fix or remove it.")
        notes.append(f"scene box: aabb {box.tolist()} -> its circumscribed sphere is the unit sphere")
        return box[0], box[1]
    aabb_scale = _number(meta, "aabb_scale", where, positive=True)
    if aabb_scale is None:
        return None
    scale = _number(meta, "scale", where, default=NGP_SCALE, positive=True)
    offset = meta.get("offset", list(NGP_OFFSET))
    try:
        offset = np.array(offset, dtype=np.float64).reshape(3)
    except (TypeError, ValueError, OverflowError):
        offset = np.full(3, np.nan)
    if not np.isfinite(offset).all():
        raise DataError(f"{where}: offset must be three finite numbers (instant-ngp); fix or remove it.")
    lo, hi = (0.0 - offset) / scale, (1.0 - offset) / scale
    notes.append(f"scene box: instant-ngp unit cube (scale {scale:g}, offset {offset.tolist()}) = [{lo.round(3).tolist()}, "
                 f"{hi.round(3).tolist()}] is the foreground (-> unit sphere); aabb_scale={aabb_scale:g}"
                 + (": the content out to that box is background (environment map)" if aabb_scale > 1 else ""))
    return lo, hi


def _box_depths(c2w: np.ndarray, box: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """[N,2] near/far depths of the box corners along each camera's viewing axis."""
    corners = np.array([[box[i][0], box[j][1], box[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    z = np.einsum("nk,pk->np", c2w[:, :3, 2], corners) - np.einsum("nk,nk->n", c2w[:, :3, 2], c2w[:, :3, 3])[:, None]
    far = np.maximum(z.max(1), 1e-3)
    return np.stack([np.maximum(z.min(1), 0.05 * far), far], 1)


def normalization(c2w: np.ndarray, masks: Any, box: Any, notes: list[str],
                  capture: Optional[str]) -> tuple[str, np.ndarray, Optional[np.ndarray]]:
    """(capture, T, LLFF depth bounds [N,2] or None) for cameras ``c2w`` [N,4,4] in the file's frame."""
    if capture is None:
        capture, reason = detect_capture(c2w, masks)
    else:
        reason = "set by the capture option"
    if capture == "forward_facing" and box is None:
        notes.append(f"forward-facing cameras ({reason}) but no scene box to bound the depths: loaded as "
                     "unbounded; add \"aabb\" to the transforms file to render in NDC")
        capture, reason = "unbounded", "forward-facing without depth bounds"
    if capture == "forward_facing":
        bounds = _box_depths(c2w, box)
        notes.append(f"capture=forward_facing ({reason}); LLFF normalization with depth bounds from the scene box")
        return capture, forward_facing_normalization(c2w, bounds), bounds
    if box is not None:
        centre, radius = (box[0] + box[1]) / 2, float(np.linalg.norm(box[1] - box[0]) / 2)
        T = similarity(1.0 / radius, centre)
    else:
        T = unit_sphere_from_cameras(c2w)
        notes.append("no scene box (aabb / aabb_scale): unit sphere around the cameras' look-at region")
    notes.append(f"capture={capture} ({reason})")
    return capture, T, None


# --------------------------------------------------------------------------- images
def _mask_source(frames: list[Frame], use_masks: bool, source: Path) -> str:
    """"files" (mask_path), "alpha" (RGBA) or "none"."""
    with_mask = [i for i, f in enumerate(frames) if f.mask is not None]
    if with_mask and len(with_mask) != len(frames):
        without = [i for i, f in enumerate(frames) if f.mask is None][:5]
        raise DataError(f"{source}: frames {without} have no mask_path but others have one: give every frame a "
                        "mask_path or none (or set data.use_masks=false).")
    if not use_masks:
        return "none"
    if with_mask:
        return "files"
    return "alpha" if any(_has_alpha(f.image) for f in frames) else "none"


def _has_alpha(path: Path) -> bool:
    try:
        with Image.open(path) as im:
            return im.mode in ("RGBA", "LA", "PA", "La", "RGBa") or (im.mode == "P" and "transparency" in im.info)
    except (OSError, ValueError, SyntaxError) as e:
        raise DataError(f"Cannot read image {path} ({e}): the file is corrupt; re-export or remove its frame.") from e


def read_frames(frames: list[Frame], size: tuple[int, int], mask_source: str, background: Sequence[float],
                notes: list[str]) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Images [N,H,W,3] and masks [N,H,W] (or None) at ``size`` = (W, H), undistorted, masks per ``mask_source``."""
    bg = np.asarray(background, dtype=np.float32)
    maps: dict[tuple, UndistortMaps] = {}
    images, masks = [], []
    for f in frames:
        m = _maps(f.camera, maps, f.image)
        rgb, alpha = read_rgba(f.image)
        rgb = remap(rgb, m)
        alpha = None if alpha is None else remap(alpha, m)
        if mask_source == "alpha":
            alpha = np.ones(rgb.shape[:2], np.float32) if alpha is None else alpha
            rgb, alpha = resize_premultiplied(rgb, alpha, size)
            rgb = np.where(alpha[..., None] > 0, rgb, bg)
            masks.append(alpha)
        else:
            if alpha is not None:
                rgb = rgb * alpha[..., None] + bg * (1.0 - alpha[..., None])
            rgb = resize_float(rgb, size)
        if mask_source == "files":
            masks.append(resize_float(remap(_read_mask(f), m), size))
        images.append(rgb.astype(np.float32))
    moved = sorted({f.camera.model for f in frames if not _maps(f.camera, maps, f.image).identity})
    if moved:
        notes.append(f"removed {'/'.join(moved)} lens distortion with OpenCV (pinhole K kept)")
    return np.stack(images), (np.stack(masks).astype(np.float32) if masks else None)


def _maps(cam: Camera, cache: dict, image: Path) -> UndistortMaps:
    key = (cam.w, cam.h, cam.fx, cam.fy, cam.cx, cam.cy, cam.model, cam.dist)
    if key not in cache:
        cache[key] = opencv_maps(cam.K, cam.dist, cam.w, cam.h, fisheye=cam.fisheye, source=str(image))
    return cache[key]


def _read_mask(f: Frame) -> np.ndarray:
    assert f.mask is not None
    if image_size(f.mask) != (f.camera.w, f.camera.h):
        w, h = image_size(f.mask)
        raise DataError(f"Mask {f.mask} is {w}x{h} but its image {f.image.name} is {f.camera.w}x{f.camera.h}: "
                        "resize the mask to the image size.")
    return read_image(f.mask, gray=True)


def _common_size(frames: list[Frame]) -> tuple[int, int]:
    first = frames[0]
    for f in frames:
        if (f.camera.w, f.camera.h) != (first.camera.w, first.camera.h):
            raise DataError(f"Mixed image sizes: {first.image} is {first.camera.w}x{first.camera.h} but {f.image} "
                            f"is {f.camera.w}x{f.camera.h}; all views of a scene must share one size: resize or "
                            "remove the odd one(s).")
    return first.camera.w, first.camera.h


def _background(background: Optional[Sequence[float]]) -> tuple[float, float, float]:
    if background is None:
        return (1.0, 1.0, 1.0)
    try:
        bg = tuple(float(x) for x in background)
    except (TypeError, ValueError):
        bg = ()
    if len(bg) != 3 or not all(0.0 <= x <= 1.0 for x in bg):
        raise ConfigError(f"background colour {background!r} is not valid: give [r, g, b] in [0, 1] "
                          "(render.background_color).")
    return bg  # type: ignore[return-value]


# --------------------------------------------------------------------------- loader
class NerfstudioConfig(LoaderConfig):
    """``data=nerfstudio``: a ``transforms.json`` scene (nerfstudio, instant-ngp, Blender synthetic)."""

    holdout_every: HoldoutEvery = Setting(
        8, description="every n-th view is held out for evaluation when the files define no split (0: none)")
    use_masks: bool = Setting(True, description="masks from each frame's mask_path or the images' alpha")
    splits: list[str] = Setting(
        ["train", "val"], description="which Blender split files to load (val and test frames are held out); "
        "[train, val, test] for all")
    capture: Optional[CaptureType] = Setting(
        None, description="force object | forward_facing | unbounded instead of detecting it")


@register("data", "nerfstudio")
@configured(NerfstudioConfig)
def load_nerfstudio(path: Any, cfg: NerfstudioConfig, context: Optional[LoaderContext] = None) -> Scene:
    """Load a ``transforms.json`` scene: ``path`` is the scene folder (``transforms.json`` or
    ``transforms_{train,val,test}.json``) or a transforms file (see the module doc; settings:
    :class:`NerfstudioConfig`; RGBA images are composited on ``context.background``, None: white)."""
    capture = cfg.capture  # null: detected below
    src = Path(path).expanduser() if path is not None else None
    root = src if src is not None and src.is_file() else require_dir(path)
    notes: list[str] = []
    files = find_transforms(root, [str(s) for s in cfg.splits])
    frames, meta = parse_frames(files, notes)
    W0, H0 = _common_size(frames)
    W1, H1 = target_size(W0, H0, choose_resolution(cfg.resolution, (W0, H0), notes))
    bg = _background((context or LoaderContext()).background)
    mask_source = _mask_source(frames, cfg.use_masks, root)
    images, masks = read_frames(frames, (W1, H1), mask_source, bg, notes)
    if mask_source == "alpha":
        notes.append("RGBA images: alpha is the mask; colours composited on the background by the datamodule")
    c2w0 = np.stack([f.c2w for f in frames])
    capture, T, bounds = normalization(c2w0, masks, scene_box(meta, files[0][1], notes), notes, capture)
    c2w = apply_similarity(T, c2w0[:, :3, :4])
    K = np.stack([f.camera.K for f in frames])
    K[:, 0, :] *= W1 / W0
    K[:, 1, :] *= H1 / H0
    split = file_split(frames, meta, root)
    if split is not None:
        notes.append(f"split from the files: {len(split[0])} train / {len(split[1])} held-out views")
    return make_scene(
        images=images, masks=masks, c2w=c2w, K=K, bounds=bounds,
        names=[_relative(f.image, root) for f in frames], normalization=T, capture=capture, source=root, notes=notes,
        hash_paths=sorted({p for _, p in files} | {f.image for f in frames} | {f.mask for f in frames if f.mask}),
        opts=dict(kind="nerfstudio", size=(W1, H1), masks=mask_source, splits=list(cfg.splits), capture=capture,
                  background=bg if mask_source != "alpha" else None),
        holdout_every=cfg.holdout_every, split=split,
    )
