"""Selfie videos / frame folders -> posed scene via COLMAP SfM (registry data "selfie").

Pipeline, as in NeRF-Art's selfie captures:

1. frames: a video is sampled at ``fps`` (15) frames per second, evenly
   subsampled to at most ``max_frames`` (100) and shrunk so the long side is at
   most ``frame_long_side`` (480 -> 270x480 portrait / 480x270 landscape; smaller
   videos keep their size). A folder of frames (``folder/`` or ``folder/images/``)
   is subsampled/resized the same way.
2. SfM with pycolmap: SIFT extraction with ONE camera shared by all frames,
   sequential matching (``matcher="exhaustive"`` for unordered frames),
   incremental mapping. Frames and model are cached in ``<base>/<name>_<hash>/``
   keyed by a SHA-256 of the input and the settings; a rerun with the same input
   loads it. Nothing is written next to the data unless asked (:func:`cache_base`):
   ``<base>`` is ``<output_root>/cache/selfie`` by default (the pipeline passes
   ``cache_root=<output_root>/cache``), ``nerfart_cache/`` beside the input with
   ``cache_dir="beside_data"``, or an explicit ``cache_dir``.
3. An existing COLMAP model (``folder/sparse/0`` with ``folder/images/``) is
   used as is, without re-running SfM.

Capture: ``"object"`` if mattes (``matte/``/``mask/``) exist next to the frames,
else ``"unbounded"`` for inward-facing trajectories, else ``"forward_facing"``.
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
from pathlib import Path
from typing import Annotated, Any, Literal, Optional

import numpy as np
from PIL import Image

from nerfart_plugin.config.components import configured
from nerfart_plugin.config.registry import register
from nerfart_plugin.config.types import Float, Fraction, Int, Limits, Resolution, Setting
from nerfart_plugin.data.colmap import ColmapModel, read_colmap_model
from nerfart_plugin.data.common import make_scene, options_key, require_dir
from nerfart_plugin.data.images import (choose_resolution, find_mask_folder, list_images, match_masks, read_image,
    target_size)
from nerfart_plugin.data.llff import forward_facing_normalization
from nerfart_plugin.data.loader import LoaderConfig, LoaderContext
from nerfart_plugin.data.normalize import apply_similarity, detect_capture, unit_sphere_from_points
from nerfart_plugin.data.scene import CaptureType, Scene
from nerfart_plugin.data.undistort import UndistortMaps, colmap_maps, remap
from nerfart_plugin.errors import ConfigError, DataError
from nerfart_plugin.utils.io import atomic_path, atomic_write_json, hash_files

log = logging.getLogger(__name__)

VIDEO_EXTS = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")
SFM_HINT = (
    "try: a video with more overlap between frames (slower motion, no motion blur), more frames "
    "(data.max_frames / data.fps), a higher data.frame_long_side, or data.matcher=exhaustive"
)


# --------------------------------------------------------------------------- frames
def _save_png(arr_u8: np.ndarray, path: Path) -> None:
    with atomic_path(path) as tmp:
        Image.fromarray(arr_u8).save(tmp, format="PNG")


def _frame_size(w: int, h: int, long_side: Optional[int]) -> tuple[int, int]:
    """(W, H) with the long side at most ``long_side`` (frames are never upsampled)."""
    return target_size(w, h, long_side) if long_side and max(w, h) > long_side else (w, h)


def _shrink(img: Any, long_side: Optional[int]) -> Any:
    size = _frame_size(img.width, img.height, long_side)
    return img if size == img.size else img.resize(size, Image.Resampling.LANCZOS)


def extract_frames(
    video: Path, out_dir: Path, fps: float = 15.0, max_frames: int = 100, long_side: Optional[int] = 480
) -> list[dict]:
    """Sample ``video`` at ``fps``, keep at most ``max_frames`` evenly, resize, save PNGs.

    Returns:
        per kept frame ``{"name": "frame_00012.png", "time": seconds}``.

    Raises:
        DataError: unreadable, zero-length or frameless video.
    """
    import av

    video = Path(video)
    if not video.is_file() or video.stat().st_size == 0:
        raise DataError(f"Video {video} is missing or empty (0 bytes): re-copy the file or fix data.path.")
    kept: list[tuple[float, Image.Image]] = []
    try:
        with av.open(str(video)) as container:
            if not container.streams.video:
                raise DataError(f"{video} has no video stream: give a video file or a folder of frames.")
            stream = container.streams.video[0]
            duration = None
            if stream.duration is not None and stream.time_base is not None:
                duration = float(stream.duration * stream.time_base)
            elif container.duration:
                duration = container.duration / 1e6
            targets = None
            if duration and duration > 0:  # choose the sample times first: convert only kept frames
                targets = np.arange(0.0, duration, 1.0 / fps)
                if len(targets) > max_frames:
                    targets = targets[np.unique(np.round(np.linspace(0, len(targets) - 1, max_frames)).astype(int))]
                targets = list(targets)
            next_t = 0.0
            last = None
            for frame in container.decode(stream):
                t = float(frame.time) if frame.time is not None else len(kept) / fps
                last = (t, frame)
                if targets is not None:
                    if not targets or t + 1e-3 < targets[0]:
                        continue
                    while targets and targets[0] <= t + 1e-3:
                        targets.pop(0)
                elif t + 1e-6 < next_t:
                    continue
                img = frame.to_image()
                img = _shrink(img, long_side)
                kept.append((t, img))
                last = None
                next_t = t + 1.0 / fps - 0.5 / 1000.0
            if targets and last is not None:  # header duration beyond the last frame (VFR phone videos)
                kept.append((last[0], _shrink(last[1].to_image(), long_side)))
    except DataError:
        raise
    except Exception as e:  # av.error.* and friends
        raise DataError(f"Cannot decode video {video} ({e.__class__.__name__}: {e}): re-encode it (e.g. ffmpeg -i in.mov out.mp4).") from e
    if not kept:
        raise DataError(f"Video {video} has no decodable frames: re-encode it or extract frames into a folder.")
    if len(kept) > max_frames:
        idx = np.unique(np.round(np.linspace(0, len(kept) - 1, max_frames)).astype(int))
        kept = [kept[i] for i in idx]
    out_dir.mkdir(parents=True, exist_ok=True)
    frames = []
    for i, (t, img) in enumerate(kept):
        name = f"frame_{i:05d}.png"
        _save_png(np.asarray(img.convert("RGB")), out_dir / name)
        frames.append({"name": name, "time": t})
    return frames


def _copy_frames(paths: list[Path], out_dir: Path, max_frames: int, long_side: Optional[int]) -> list[dict]:
    """Subsample a frame folder evenly to ``max_frames`` and save resized PNG copies."""
    if len(paths) > max_frames:
        idx = np.unique(np.round(np.linspace(0, len(paths) - 1, max_frames)).astype(int))
        paths = [paths[i] for i in idx]
    out_dir.mkdir(parents=True, exist_ok=True)
    frames = []
    for p in paths:

        with Image.open(p) as im:
            size = _frame_size(im.width, im.height, long_side)
        arr = read_image(p, size)
        name = p.stem + ".png"
        _save_png((arr * 255 + 0.5).astype(np.uint8), out_dir / name)
        frames.append({"name": name, "source": p.name})
    return frames


# --------------------------------------------------------------------------- SfM
def _pycolmap_version() -> str:
    """The installed pycolmap's version (part of the SfM cache key: the cameras are a function of it)."""
    try:
        import pycolmap
    except ImportError:  # a cache of frames that needs no SfM yet; run_sfm says how to install it
        return "none"
    return str(getattr(pycolmap, "__version__", "unknown"))


def run_sfm(
    image_dir: Path,
    out_dir: Path,
    matcher: str = "sequential",
    camera_model: str = "SIMPLE_RADIAL",
    overlap: int = 10,
    seed: int = 0,
    num_threads: int = 1,
) -> Path:
    """COLMAP SfM on ``image_dir``: SIFT, one shared camera, sequential/exhaustive matching,
    incremental mapping. Writes the largest model to ``out_dir/sparse/0`` atomically
    (file by file) and returns that folder.

    Determinism: with ``num_threads=1`` (the default) the cameras are a function of
    the frames, ``seed`` and the pycolmap version: every RANSAC, the mapper and
    COLMAP's global PRNG are seeded, and each step runs on one thread. With more
    threads, feature extraction writes images to the database in completion order
    and matching verifies pairs in completion order; both change the result from
    run to run (measured on Beer.mp4: focal 414.6-417.3 px from identical frames).

    Raises:
        DataError: no model could be reconstructed.
    """
    import pycolmap

    n_images = len(list_images(image_dir))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="sfm_", dir=out_dir))
    try:
        db = work / "database.db"
        pycolmap.set_random_seed(seed)
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = num_threads
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = num_threads
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = seed
        verification.ransac.num_threads = 1
        log.info("SfM: extracting SIFT features from %d frames in %s", n_images, image_dir)
        pycolmap.extract_features(db, image_dir, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        log.info("SfM: %s matching", matcher)
        if matcher == "sequential":
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = overlap
            pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                                      verification_options=verification, device=pycolmap.Device.cpu)
        elif matcher == "exhaustive":
            pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification,
                                      device=pycolmap.Device.cpu)
        else:
            raise DataError(f"Unknown data.matcher={matcher!r}: use 'sequential' (videos) or 'exhaustive'.")
        log.info("SfM: incremental mapping")
        opts = pycolmap.IncrementalPipelineOptions()
        opts.random_seed = seed
        opts.num_threads = num_threads
        opts.mapper.random_seed = seed
        opts.mapper.num_threads = num_threads
        recs = pycolmap.incremental_mapping(db, image_dir, work / "models", options=opts)
        if not recs:
            raise DataError(
                f"COLMAP could not reconstruct any camera from the {n_images} frames in {image_dir}; {SFM_HINT}."
            )
        best = max(recs.values(), key=lambda r: r.num_reg_images())
        tmp_model = work / "best"
        tmp_model.mkdir()
        best.write(str(tmp_model))
        final = out_dir / "sparse" / "0"
        for f in sorted(tmp_model.iterdir()):
            with atomic_path(final / f.name) as tmp:
                shutil.copyfile(f, tmp)
        return final
    finally:
        shutil.rmtree(work, ignore_errors=True)


def check_sfm_camera_model(name: str) -> str:
    """``name`` if COLMAP can fit it to the frames and the result can be undistorted, else ConfigError."""
    import pycolmap

    usable = [m for m in pycolmap.CameraModelId.__members__ if m not in ("INVALID", "EQUIRECTANGULAR")]
    if name not in usable:
        raise ConfigError(f"data.camera_model={name!r} is not a COLMAP camera model this loader can use; pick one of "
                          f"{', '.join(usable)} (SIMPLE_RADIAL for phone videos, OPENCV_FISHEYE for action cameras).")
    return name


# --------------------------------------------------------------------------- loader
def _undistortion(model: ColmapModel, source: Path, notes: list[str]) -> list[UndistortMaps]:
    """Undistortion tables per image (one per COLMAP camera), built with pycolmap for any model.

    Raises:
        DataError: a camera model without a pinhole view (spherical), naming it.
    """
    by_camera: dict[int, UndistortMaps] = {}
    for i, cid in enumerate(model.camera_ids):
        if cid not in by_camera:
            by_camera[cid] = colmap_maps(model.camera(i), f"{source} (camera {cid})")
    maps = [by_camera[c] for c in model.camera_ids]
    moved = sorted({model.camera_models[i] for i, m in enumerate(maps) if not m.identity})
    if moved:
        valid = min(m.valid_fraction for m in maps)
        notes.append(f"removed {'/'.join(moved)} lens distortion from the images with pycolmap's camera model "
                     f"(pinhole K kept; {valid:.1%} of each view maps inside the source image, the rest is 0)")
    return maps


def _prepare(
    root: Path,
    fps: float,
    max_frames: int,
    frame_long_side: Optional[int],
    matcher: str,
    camera_model: str,
    cache_dir: Optional[Any],
    notes: list[str],
    sfm_seed: int = 0,
    sfm_threads: int = 1,
    cache_root: Optional[Any] = None,
) -> tuple[Path, Path, list[Path], Optional[Path]]:
    """Return (image folder, model folder, files defining the scene, mask folder)."""
    settings = dict(fps=fps, max_frames=max_frames, long=frame_long_side, matcher=matcher, cam=camera_model,
                    seed=sfm_seed, threads=sfm_threads, v=3, pycolmap=_pycolmap_version())
    if root.is_file():
        if root.suffix.lower() not in VIDEO_EXTS:
            raise DataError(f"{root} is not a video ({'/'.join(VIDEO_EXTS)}) nor a folder of frames: fix data.path.")
        inputs, mask_dir, frame_paths = [root], None, None
    else:
        if (root / "sparse" / "0").is_dir() and (root / "images").is_dir():
            notes.append(f"using the existing COLMAP model {root / 'sparse' / '0'} as is")
            model = root / "sparse" / "0"
            files = [p for p in model.iterdir() if p.is_file()]
            return root / "images", model, files, find_mask_folder(root)
        frame_dir = root / "images" if (root / "images").is_dir() else root
        frame_paths = list_images(frame_dir, notes)
        inputs, mask_dir = frame_paths, find_mask_folder(root)
    if not root.is_file() and len(frame_paths) < 3:
        raise DataError(f"Only {len(frame_paths)} frame(s) in {frame_dir}: SfM needs many overlapping views (>= 20).")
    key = hash_files(inputs, extra=options_key(**settings))[:16]
    cache = cache_base(root, cache_dir, cache_root) / f"{root.stem}_{key}"
    image_dir, model_dir, meta_path = cache / "images", cache / "sparse" / "0", cache / "frames.json"
    if meta_path.is_file() and (model_dir / "images.bin").is_file():
        notes.append(f"loaded cached frames and SfM from {cache}")
    else:
        cache.mkdir(parents=True, exist_ok=True)
        if root.is_file():
            frames = extract_frames(root, image_dir, fps, max_frames, frame_long_side)
            notes.append(f"extracted {len(frames)} frames at <= {fps:g} fps from {root.name}")
        else:
            frames = _copy_frames(frame_paths, image_dir, max_frames, frame_long_side)
        run_sfm(image_dir, cache, matcher=matcher, camera_model=camera_model, seed=sfm_seed, num_threads=sfm_threads)
        atomic_write_json(meta_path, {"source": str(root), "settings": settings, "frames": frames})
        notes.append(f"ran COLMAP SfM ({matcher} matching, one shared {camera_model} camera); cached in {cache}")
    files = [meta_path, *[p for p in model_dir.iterdir() if p.is_file()]]
    return image_dir, model_dir, files, mask_dir


def cache_base(root: Path, cache_dir: Optional[Any] = None, cache_root: Optional[Any] = None) -> Path:
    """The folder that holds the ``<name>_<hash>/`` frame + SfM caches of input ``root``.

    Args:
        root: the video file or frame folder.
        cache_dir: None or ``"auto"``: ``<cache_root>/selfie``; ``"beside_data"``:
            ``nerfart_cache/`` next to the video (inside a frame folder), the only
            choice that writes into the data folder; anything else: that folder.
        cache_root: the project's cache folder; the pipeline passes
            ``<output_root>/cache``; None: ``outputs/cache`` (the default
            ``output_root``, relative to the working directory).
    """
    if cache_dir is None or str(cache_dir) in ("auto", ""):
        return Path(cache_root if cache_root is not None else Path("outputs") / "cache").expanduser() / "selfie"
    if str(cache_dir) == "beside_data":
        return (root.parent if root.is_file() else root) / "nerfart_cache"
    return Path(cache_dir).expanduser()


def selfie_cache_meta(scene: Scene) -> Optional[dict]:
    """The cache's ``frames.json`` (frame names and video times) for a selfie scene, if any."""
    for note in scene.notes:
        for marker in ("cached in ", "cached frames and SfM from "):
            if marker in note:
                p = Path(note.split(marker, 1)[1]) / "frames.json"
                if p.is_file():
                    return json.loads(p.read_text())
    return None


#: COLMAP camera models of the shared camera (distortion of the radial/OpenCV ones is removed)

class SelfieConfig(LoaderConfig):
    """``data=selfie``: a selfie video, a folder of frames, or a COLMAP scene folder (``images/`` + ``sparse/0``)."""

    resolution: Resolution = Setting(
        "auto", description="long side of the returned images: auto: min(native, 480) (the paper's 270x480 for "
        "540x960 frames; video frames stay at frame_long_side); null: the frames' size; N: pixels")
    fps: Annotated[Float, Limits(gt=0.0, le=1000.0)] = Setting(15.0, description="frames sampled per second of video")
    max_frames: Annotated[Int, Limits(ge=3, le=100_000)] = Setting(100, description="at most this many frames")
    frame_long_side: Optional[Annotated[Int, Limits(ge=16, le=16384)]] = Setting(
        480, description="long side of the extracted video frames (pixels); null: the video's own")
    matcher: Literal["sequential", "exhaustive"] = Setting(
        "sequential", description="COLMAP feature matching: sequential (video order) | exhaustive")
    camera_model: str = Setting(
        "SIMPLE_RADIAL", description="COLMAP model of the one shared camera; distortion is removed from the images")
    min_registered: Fraction = Setting(0.5, description="the least share of frames SfM must register")
    cache_dir: Optional[Any] = Setting(
        None, description="where the frames and SfM cache goes: null: <output_root>/cache/selfie; beside_data: "
        "nerfart_cache/ next to the input; or a folder")
    capture: Optional[CaptureType] = Setting(
        None, description="force object | forward_facing | unbounded instead of detecting it")
    sfm_seed: Annotated[Int, Limits(ge=0, le=2**31 - 1)] = Setting(
        0, description="seed of every random choice in COLMAP (RANSAC, mapper)")
    sfm_threads: Annotated[Int, Limits(ge=1, le=1024)] = Setting(
        1, description="threads of each SfM step; 1 makes the cameras a function of the frames, more is faster "
        "but not reproducible")


@register("data", "selfie")
@configured(SelfieConfig)
def load_selfie(path: Any, cfg: SelfieConfig, context: Optional[LoaderContext] = None) -> Scene:
    """Load a selfie video, a folder of frames (``folder/`` or ``folder/images/``) or a folder with ``images/`` and
    ``sparse/0`` (see the module doc; settings: :class:`SelfieConfig`; ``context.cache_root``: the project's cache
    folder, the pipeline's ``<output_root>/cache``)."""
    capture = cfg.capture  # null: detected below
    if path is None:
        raise DataError("No input given for data=selfie: set data.path=/path/to/video.mp4 (or a folder of frames).")
    check_sfm_camera_model(cfg.camera_model)
    root = Path(path).expanduser()
    if not root.is_file():
        root = require_dir(root, "selfie folder")
    notes: list[str] = []
    image_dir, model_dir, files, mask_dir = _prepare(
        root, cfg.fps, cfg.max_frames, cfg.frame_long_side, cfg.matcher, cfg.camera_model, cfg.cache_dir, notes,
        sfm_seed=int(cfg.sfm_seed), sfm_threads=int(cfg.sfm_threads), cache_root=(context or LoaderContext()).cache_root,
    )
    model: ColmapModel = read_colmap_model(model_dir)
    frames = list_images(image_dir)
    n_total, n_reg = len(frames), len(model.names)
    if n_reg < max(3, cfg.min_registered * n_total):
        raise DataError(
            f"COLMAP registered only {n_reg} of {n_total} frames from {root} (need >= {cfg.min_registered:.0%}); "
            f"{SFM_HINT}. Delete {model_dir.parent.parent} to redo SfM."
        )
    if n_reg < n_total:
        notes.append(f"SfM registered {n_reg} of {n_total} frames; the others are dropped")
    by_name = {p.name: p for p in frames}
    missing = [n for n in model.names if n not in by_name]
    if missing:
        raise DataError(
            f"COLMAP model {model_dir} names images missing from {image_dir} ({missing[:3]}); "
            "the model does not belong to these frames: delete the cache or fix the folder."
        )
    paths = [by_name[n] for n in model.names]
    W0, H0 = int(model.sizes[0][0]), int(model.sizes[0][1])
    if any(tuple(s) != (W0, H0) for s in model.sizes):
        raise DataError(f"COLMAP model {model_dir} has cameras of different sizes; use one image size for all frames.")
    W1, H1 = target_size(W0, H0, choose_resolution(cfg.resolution, (W0, H0), notes))
    sx, sy = W1 / W0, H1 / H0
    maps = _undistortion(model, model_dir, notes)
    imgs = []
    for i, p in enumerate(paths):
        arr = read_image(p)
        if arr.shape[:2] != (H0, W0):
            raise DataError(f"{p} is {arr.shape[1]}x{arr.shape[0]} but its COLMAP camera is {W0}x{H0}: images and model do not match.")
        imgs.append(remap(arr, maps[i]))
    images = np.stack(imgs)
    masks, mask_paths = None, []
    if cfg.use_masks and mask_dir is not None:
        mask_paths = match_masks(paths, list_images(mask_dir, notes), notes)
        masks = np.stack([remap(read_image(p, (W0, H0), gray=True), maps[i]) for i, p in enumerate(mask_paths)])
    if (W1, H1) != (W0, H0):
        import torch
        import torch.nn.functional as F

        images = F.interpolate(torch.from_numpy(images).permute(0, 3, 1, 2), size=(H1, W1), mode="bilinear",
                               antialias=True).permute(0, 2, 3, 1).clamp(0, 1).numpy()
        if masks is not None:
            masks = F.interpolate(torch.from_numpy(masks)[:, None], size=(H1, W1), mode="bilinear",
                                  antialias=True)[:, 0].clamp(0, 1).numpy()
    K = np.stack([m.K for m in maps])
    K[:, 0, :] *= sx
    K[:, 1, :] *= sy
    if capture is None:
        capture, reason = detect_capture(model.c2w, masks)
    else:
        reason = "set by the capture option"
    # per-camera depth range of the sparse points each camera observes
    depths_lo, depths_hi = [], []
    for i, (_, idx) in enumerate(model.observations):
        pts = model.points[idx] if len(idx) else model.points
        w2c = np.linalg.inv(model.c2w[i])
        z = pts @ w2c[2, :3] + w2c[2, 3]
        z = z[z > 0]
        z = z if len(z) else np.array([1.0, 10.0])
        depths_lo.append(np.percentile(z, 1))
        depths_hi.append(np.percentile(z, 99))
    bounds = np.stack([np.array(depths_lo), np.array(depths_hi)], 1)
    if capture == "forward_facing":
        T = forward_facing_normalization(model.c2w, bounds)
    else:
        T = unit_sphere_from_points(model.points, model.c2w)
    c2w = apply_similarity(T, model.c2w)
    notes.append(f"capture={capture} ({reason})")
    return make_scene(
        images=images, masks=masks, c2w=c2w, K=K, names=model.names, normalization=T, capture=capture,
        source=root, notes=notes, hash_paths=[*files, *paths, *mask_paths], bounds=bounds,
        holdout_every=cfg.holdout_every, opts=dict(kind="selfie", size=(W1, H1), use_masks=cfg.use_masks, capture=capture))
