"""A finished run opened for rendering: :class:`Run` (render, paths, meshes, the strength dial), :func:`mix`
and :func:`open_run` (the public face is :mod:`nerfart_plugin.api`)."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Optional, Sequence, Union

import numpy as np
import torch
import yaml

from nerfart_plugin.cameras.capture import CaptureCameras, scale_intrinsics
from nerfart_plugin.cameras.path import RenderPath, frame_size, resolve_path, scaled_K, write_camera_path
from nerfart_plugin.config.migrate import to_current
from nerfart_plugin.config.schema import RunConfig
from nerfart_plugin.config.validate import parse_config
from nerfart_plugin.data.datamodule import datamodule_of
from nerfart_plugin.data.setup import SceneSetup
from nerfart_plugin.errors import CheckpointError, ConfigError, NerfArtError
from nerfart_plugin.export import MeshExtractor
from nerfart_plugin.export.video import write_video
from nerfart_plugin.export.world_frame import mesh_in_frame
from nerfart_plugin.rendering.frames import render_cameras
from nerfart_plugin.fields.composite import CompositeField, RegionMask
from nerfart_plugin.regions.region import DEFAULT_RESOLUTION, Region
from nerfart_plugin.results.blend import (blend_tag, blended_renderer, check_strength, check_weights,
                                          refresh_occupancy)
from nerfart_plugin.results.record import RunRecord, migrate
from nerfart_plugin.systems.base import build_renderer
from nerfart_plugin.systems.checkpoints import META_KEY, hash_mismatch, load_checkpoint, prefixed_state
from nerfart_plugin.utils.device import pick_device
from nerfart_plugin.utils.images import save_image
from nerfart_plugin.utils.io import hash_files, slug

log = logging.getLogger("nerfart_plugin")

__all__ = ["Run", "open_run", "mix", "composite_renderer"]

#: the region a stylization was trained in, in its run folder (:class:`~nerfart_plugin.regions.Region`)
REGION_FILE = "region.npz"


@dataclass
class Run:
    """A finished run folder, ready to render.

    Attributes:
        folder: the run folder; checkpoint: the checkpoint read.
        kind: "reconstruction" or "stylization"; record: its ``run.json`` (:mod:`nerfart_plugin.results.record`).
        config: its typed config; metrics: its ``metrics.json``.
        renderer: the trained renderer (eval mode, on ``device``).
        cameras: the capture's cameras (normalized frame; from ``cameras.json``, else from the data).
        stamp: the file suffix of a run whose guidance was not a real CLIP (``_VERIFY-imagenet``), else "".
        weights: the blend this Run renders (:mod:`nerfart_plugin.results.blend`): ``(1.0,)`` the run as trained,
            ``(s,)`` the strength dial, one weight per run for a mix; mixed: the folders of a mix's runs.
        region: the region the stylization applies in (the one it was trained in, ``region.npz`` in its folder,
            or one applied by :meth:`with_region`); None: the whole scene. ``renderer`` then renders the
            composite of the source and the stylized field inside it (:mod:`nerfart_plugin.fields.composite`).
        own: the renderer its checkpoint holds (the stylized field alone; ``renderer`` when nothing is composed).
        applied: the region was applied after training (:meth:`with_region`), which its output names say.
    """

    folder: Path
    checkpoint: Path
    kind: str
    config: RunConfig
    metrics: dict
    renderer: Any
    cameras: CaptureCameras
    device: torch.device
    stamp: str = ""
    weights: tuple[float, ...] = (1.0,)
    mixed: tuple[str, ...] = ()
    record: Optional[RunRecord] = None
    region: Optional[Region] = None
    own: Any = None
    applied: bool = False
    _source: Optional["Run"] = field(default=None, repr=False)

    # ------------------------------------------------------------------ what it is
    @property
    def resolution(self) -> int:
        """The long side (pixels) the run was trained and evaluated at: a stylization's resolution, else the
        images'."""
        native = max(self.cameras.height, self.cameras.width)
        if self.kind == "stylization" and self.config.stylize.resolution != "auto":
            return int(self.config.stylize.resolution)
        return native

    @property
    def source(self) -> "Run":
        """The reconstruction a stylization started from (its ``final.ckpt``, as the run recorded it)."""
        if self.kind != "stylization":
            raise NerfArtError(f"{self.folder} is a reconstruction: it has no source run.")
        if self._source is None:
            record = self.record or RunRecord.read(self.folder)
            found = record.source_folder(self.folder)
            if found is None or not (found / "final.ckpt").is_file():
                where = " or ".join(dict.fromkeys(str(v) for v in record.source.values())) or "not recorded"
                raise NerfArtError(f"{self.folder}: its source reconstruction ({where}) is not on this machine. "
                                   "Copy that reconstruction folder back (beside this run's stylizations/ folder, "
                                   "under reconstructions/), then run the same command again.")
            self._source = open_run(found, device=str(self.device))
        return self._source

    @property
    def tag(self) -> str:
        """The part of output names that tells blends apart: "" as trained, ``-s0.50``, ``-mix0.50_0.50-<hash>``."""

        tag = blend_tag(self.weights, self.mixed)
        return tag + (f"-region{self.region.content_hash[:6]}" if self.region is not None and self.applied else "")

    def with_strength(self, strength: float) -> "Run":
        """This stylization at ``strength`` (0: the source, 1: as trained, up to 2: past it), without retraining
        (:mod:`nerfart_plugin.results.blend`); a Run that renders, meshes and writes like any other."""

        if self.kind != "stylization" or self.weights != (1.0,):
            raise NerfArtError(f"{self.folder}: a strength (strength=, Run.with_strength) applies to a stylization as "
                               f"trained, not to a {'blend' if self.kind == 'stylization' else 'reconstruction'}: give "
                               "render.run= (or source_checkpoint=) a folder under outputs/stylizations/.")
        return mix([self], [check_strength(strength)])

    def with_region(self, region: Region) -> "Run":
        """This stylization inside ``region`` only (:class:`~nerfart_plugin.regions.Region`), the source
        everywhere else, without retraining: the composite at render time, at any strength
        (``run.with_region(r).with_strength(0.5)``). A Run that renders, meshes and writes like any other."""
        if self.kind != "stylization" or len(self.weights) != 1:
            raise NerfArtError(f"{self.folder}: a region (region=, Run.with_region) applies to a stylization (at any "
                               f"strength), not to a {'mix' if self.kind == 'stylization' else 'reconstruction'}: give "
                               "render.run= (or source_checkpoint=) a folder under outputs/stylizations/.")
        if self.own is None and self.weights != (1.0,):
            raise NerfArtError(f"{self.folder}: apply the region first, then the strength: "
                               "run.with_region(region).with_strength(s).")
        if not isinstance(region, Region):
            raise ConfigError(f"with_region: a nerfart_plugin.api.Region, not {type(region).__name__}.")
        own = self.own if self.own is not None else self.renderer
        renderer = composite_renderer(own, self.source.renderer, [(own.field, self.weights[0], region)], self.cameras)
        return replace(self, renderer=renderer, region=region, own=own, applied=True)

    def scene(self):
        """The capture again (:class:`~nerfart_plugin.data.scene.Scene`: photos, masks, cameras), loaded
        from the run's ``data`` settings (the data must be where the run found it)."""
        return datamodule_of(self.config).load()

    # ------------------------------------------------------------------ cameras
    def camera_path(self, path: Union[str, RenderPath] = "orbit", frames: int = 120, resolution: Optional[int] = None,
                    path_frame: str = "world") -> RenderPath:
        """The cameras of ``path`` (orbit | spiral | training | a camera_path.json, see
        :func:`~nerfart_plugin.cameras.path.resolve_path`) at ``resolution`` (long side; None: the run's)."""
        if isinstance(path, RenderPath):
            return path
        file_size = resolution is None and path not in ("orbit", "spiral", "training")
        return resolve_path(self.cameras, path, frames, None if file_size else (resolution or self.resolution), path_frame)

    def camera(self, camera: Union[int, np.ndarray, torch.Tensor], resolution: Optional[int] = None,
               frame: str = "world", K: Optional[np.ndarray] = None) -> RenderPath:
        """One camera: a view index of the capture, or a camera-to-world matrix [3,4] / [4,4] (OpenCV axes)
        in ``frame`` ("world": the capture's, as the exported meshes; "normalized") with the intrinsics ``K``
        [3,3] at the capture's image size (default: training view 0's)."""
        H, W = frame_size(self.cameras, resolution or self.resolution)
        if isinstance(camera, (int, np.integer)):
            i = int(camera)
            if not 0 <= i < len(self.cameras.c2w):
                raise NerfArtError(f"camera {i}: the capture has views 0..{len(self.cameras.c2w) - 1}.")
            c2w, Ks = self.cameras.c2w[i:i + 1], scaled_K(self.cameras, [i], H, W)
        else:
            m = np.asarray(camera.detach().cpu() if torch.is_tensor(camera) else camera, dtype=np.float64)
            if m.shape not in ((3, 4), (4, 4)):
                raise NerfArtError(f"camera: expected a [3,4] or [4,4] camera-to-world matrix, got shape {m.shape}.")
            c2w = m[None, :3, :4]
            c2w = self.cameras.from_world(c2w) if frame == "world" else c2w
            ref = self.cameras.train_ids[:1] or [0]
            Ks = scaled_K(self.cameras, ref, H, W)
            if K is not None:
                Kt = torch.as_tensor(np.asarray(K, dtype=np.float64), dtype=torch.float32)
                Ks = scale_intrinsics(Kt, W / self.cameras.width, H / self.cameras.height)[None]
        return RenderPath("camera", torch.as_tensor(c2w, dtype=torch.float32), Ks, H, W)

    # ------------------------------------------------------------------ rendering
    def render(self, camera: Union[int, np.ndarray, torch.Tensor], resolution: Optional[int] = None,
               channels: Sequence[str] = ("rgb",), frame: str = "world") -> dict[str, np.ndarray]:
        """One view (see :meth:`camera`) -> channel -> [H,W,3] uint8 (channels of
        :mod:`nerfart_plugin.rendering.frames`)."""
        return {k: v[0] for k, v in self.render_path(self.camera(camera, resolution, frame), channels=channels,
                                                     progress=False).items()}

    def render_path(self, path: Union[str, RenderPath] = "orbit", frames: int = 120, resolution: Optional[int] = None,
                    channels: Sequence[str] = ("rgb",), path_frame: str = "world",
                    progress: bool = True, on_frame: Optional[Callable[[int, int], None]] = None
                    ) -> dict[str, list[np.ndarray]]:
        """Every camera of ``path`` (:meth:`camera_path`) -> channel -> list of [H,W,3] uint8 frames
        (``on_frame(done, total)`` after each camera)."""

        rp = self.camera_path(path, frames, resolution, path_frame)
        if "side" in channels and self.kind != "stylization":
            raise ConfigError(f"render.channels=side shows source | stylized, but {self.folder} is a reconstruction: "
                              "render a stylization run, or drop side.")
        source = self.source.renderer if "side" in channels else None
        label = "stylized" + (f" ({self.stamp.strip('_')})" if self.stamp else "") + self.tag.replace("-", " ")
        cams = self.cameras
        return render_cameras(self.renderer, rp, ndc=cams.ndc, near=float(cams.near.min()), far=float(cams.far.max()),
                              chunk=self.config.render.chunk, device=self.device, channels=channels, source=source,
                              labels=("source", label), progress=progress, on_frame=on_frame)

    def write_render(self, out_dir: Union[str, Path], path: Union[str, RenderPath] = "orbit", frames: int = 120,
                     resolution: Optional[int] = None, channels: Sequence[str] = ("rgb",), fps: Optional[int] = None,
                     png: bool = False, path_frame: str = "world",
                     on_frame: Optional[Callable[[int, int], None]] = None) -> dict[str, Any]:
        """Render ``path`` and write ``<out_dir>/<channel><stamp>.mp4`` per channel (and, ``png``, the frames
        as ``<channel>/00000.png`` ...) plus ``camera_path.json`` (nerfstudio format, world frame) to render the
        same path again or edit it. Returns what was written."""

        out = Path(out_dir)
        rp = self.camera_path(path, frames, resolution, path_frame)
        fps = int(fps or rp.fps or 24)
        rendered = self.render_path(rp, channels=channels, on_frame=on_frame)
        files: dict[str, Any] = {"camera_path": str(write_camera_path(rp, self.cameras, out / "camera_path.json", fps))}
        for channel, images in rendered.items():
            name = f"{channel}{self.tag}{self.stamp}"
            files[channel] = str(write_video(images, out / f"{name}.mp4", fps=fps))
            if png:
                for i, img in enumerate(images):
                    save_image(img, out / name / f"{i:05d}.png")
        log.info("rendered %d frames of %s (%dx%d) -> %s", len(rp), rp.name, rp.width, rp.height, out)
        return {"dir": str(out), "frames": len(rp), "width": rp.width, "height": rp.height, "fps": fps, "files": files}

    def render_folder(self, path: RenderPath) -> Path:
        """Where ``stage=render`` writes ``path``: ``<run>/render/<path>-<F>f-<W>x<H><blend tag>``."""

        return self.folder / "render" / f"{slug(path.name)}-{len(path)}f-{path.width}x{path.height}{self.tag}"

    # ------------------------------------------------------------------ geometry
    def mesh(self, resolution: int = 128, frame: str = "world", level: Optional[float] = None):
        """The field's surface by marching cubes (``trimesh.Trimesh`` with vertex colours) in ``frame``
        ("world": the capture's, as the pipeline's exports; "normalized": the training frame)."""

        ec = self.config.export
        field = self.renderer.field
        ex = MeshExtractor(resolution=int(resolution), bound=float(field.bound), chunk=ec.chunk,
                           level=ec.level if level is None else level, remove_floaters=ec.remove_floaters)
        return mesh_in_frame(ex.extract(field), frame, self.cameras)


def mix(runs: Sequence[Run], weights: Sequence[float]) -> Run:
    """Stylizations of one source combined: ``θ_src + Σ w_i (θ_i − θ_src)`` (:mod:`nerfart_plugin.results.blend`;
    each weight in ``blend.WEIGHT_RANGE``). Returns a Run like the first one (its folder, settings and
    cameras) rendering the blend. Runs whose source checkpoints differ in content are refused."""

    weights = check_weights(weights, len(runs))
    for r in runs:
        if r.kind != "stylization" or r.weights != (1.0,):
            raise ConfigError(f"mix: {r.folder} is not a stylization as trained; mix stylizations of one source.")
    if any(r.region is not None for r in runs):  # region by region: each style inside its own region
        return _mix_regions(runs, weights)
    source = runs[0].source
    content = _content(source.checkpoint) if len(runs) > 1 else ""  # one run (the strength dial): its own source
    for r in runs[1:]:
        if _content(r.source.checkpoint) != content:
            raise ConfigError(f"mix: the runs stylize different sources: {source.checkpoint} and "
                              f"{r.source.checkpoint} differ in content; mix stylizations of the same reconstruction.")
    renderer = blended_renderer(runs[0].renderer, source.renderer, [r.renderer for r in runs], weights)
    return replace(runs[0], renderer=renderer, weights=tuple(weights), mixed=tuple(str(r.folder) for r in runs),
                   _source=source)


def _mix_regions(runs: Sequence[Run], weights: Sequence[float]) -> Run:
    """Stylizations of one source, each inside its region (a whole-scene one everywhere) at its weight: the
    composite ``out_src + Σ w_i m_i (out_i − out_src)`` (:class:`~nerfart_plugin.fields.composite.CompositeField`)."""
    source = runs[0].source
    for r in runs[1:]:
        if _content(r.source.checkpoint) != _content(source.checkpoint):
            raise ConfigError(f"mix: the runs stylize different sources: {source.checkpoint} and "
                              f"{r.source.checkpoint} differ in content; mix stylizations of the same reconstruction.")
    owns = [r.own if r.own is not None else r.renderer for r in runs]
    parts = [(own.field, w, r.region) for own, w, r in zip(owns, weights, runs)]
    renderer = composite_renderer(owns[0], source.renderer, parts, runs[0].cameras)
    return replace(runs[0], renderer=renderer, weights=tuple(weights), mixed=tuple(str(r.folder) for r in runs),
                   own=owns[0], applied=False, _source=source)


def composite_renderer(own: Any, source: Any, parts: Sequence[tuple[Any, float, Optional[Region]]], cameras: Any,
                       share_occupancy: bool = False, resolution: int = DEFAULT_RESOLUTION) -> Any:
    """``own`` (a stylization's renderer: its sampling settings) rendering the source's field with ``parts``
    [(field, weight, region or None: everywhere)] composed in (:class:`~nerfart_plugin.fields.composite.CompositeField`),
    each region bound to the capture's frame (``cameras``) on a ``resolution``^3 grid. The occupancy grid is
    estimated afresh from the composite unless it is shared with ``own`` (a regional run's own grid: trained on
    that very composite)."""
    bound = float(source.field.bound)
    masks = [RegionMask.everywhere(bound) if region is None else region.bind(cameras.field_to_world, bound, resolution)
             for _, _, region in parts]
    composite = CompositeField(source.field, [(f, float(w), m) for (f, w, _), m in zip(parts, masks)])
    device = next(own.parameters()).device
    out = own.with_field(composite.to(device), share_occupancy=share_occupancy)
    if not share_occupancy and out.occupancy is not None:
        if source.occupancy is not None:  # the source's cells where no region reaches, re-estimated elsewhere
            out.occupancy.load_state_dict(source.occupancy.state_dict())
            out.occupancy.keep.copy_(composite.cells_outside(out.occupancy))
        refresh_occupancy(out)
    return out.eval()


def _content(path: Path) -> str:
    return hash_files([Path(path)])


def read_renderer(checkpoint: Path, cfg: RunConfig) -> Any:
    """The trained renderer of a run's ``checkpoint`` (eval mode, on the CPU), rebuilt from ``cfg`` and the scene
    setup the checkpoint records; read without running code."""
    ckpt = load_checkpoint(checkpoint, fix=f"If {checkpoint.name} was damaged, run the command that made this run "
                                           "again: it sets the damaged file aside and trains again from the run's "
                                           "last.ckpt (nothing else in the folder is touched).")
    meta = ckpt.get(META_KEY)
    if not isinstance(meta, dict) or "setup" not in meta:
        raise NerfArtError(f"{checkpoint} records no scene setup (written by another version); rebuild its renderer "
                           "with nerfart_plugin.run.factories.build_scene(cfg) and load_renderer_state(checkpoint, "
                           "scene).")
    renderer = build_renderer(cfg, SceneSetup(**meta["setup"]))
    renderer.load_state_dict(prefixed_state(ckpt, "renderer."))
    return renderer.eval()


def open_run(folder: Union[str, Path], checkpoint: str = "final.ckpt", device: str = "auto") -> Run:
    """Open a reconstruction or stylization folder (or pass a checkpoint file in one) for rendering.

    Args:
        folder: ``outputs/reconstructions/<run>`` or ``outputs/stylizations/<run>`` (or a ``.ckpt`` in it).
        checkpoint: the checkpoint to read (``last.ckpt`` for an unfinished run).
        device: auto (CUDA, then MPS, then CPU) | cpu | cuda | cuda:N | mps.
    """
    folder = Path(folder).expanduser()
    if folder.suffix == ".ckpt":
        folder, checkpoint = folder.parent, folder.name
    if not (folder / "config.yaml").is_file() or not (folder / checkpoint).is_file():
        raise NerfArtError(f"{folder} is not a run folder with {checkpoint} (and config.yaml): give render.run= "
                           "(source_checkpoint=, mix.runs=, the viewer, open_run) a folder under "
                           "outputs/reconstructions/ or outputs/stylizations/.")
    why = hash_mismatch(folder / checkpoint)
    if why:  # without a stored hash, read_renderer's load below is the check
        raise CheckpointError(f"{folder / checkpoint} is damaged ({why}). Run the command that made this run again: "
                              "it sets the damaged file aside and trains again from the run's last.ckpt (nothing else "
                              "in the folder is touched).")
    cfg = read_config(folder / "config.yaml")
    region = Region.load(folder / REGION_FILE) if (folder / REGION_FILE).is_file() else None
    renderer = read_renderer(folder / checkpoint, cfg)
    metrics = json.loads((folder / "metrics.json").read_text()) if (folder / "metrics.json").is_file() else {}
    record = migrate(folder)
    cams_file = folder / "cameras.json"
    if cams_file.is_file():
        cameras = CaptureCameras.from_json(json.loads(cams_file.read_text()))
    else:  # a run written before cameras.json: the cameras from the data
        log.info("%s has no cameras.json: reading the cameras from its data (%s)", folder, cfg.data.path)
        dm = datamodule_of(cfg)
        cameras = CaptureCameras.from_scene(dm.load(), dm.ndc)
    if record.kind == "stylization":  # rendered as the stylization was evaluated
        renderer.reduce_samples(cfg.stylize.num_samples)
    dev = pick_device(device)
    run = Run(folder, folder / checkpoint, record.kind, cfg, metrics, renderer.to(dev).eval(), cameras, dev,
              stamp=metrics.get("stamp") or "", record=record)
    if region is None:
        return run
    # a regional stylization renders as it trained: the source with the stylized field inside its region,
    # on the occupancy grid it trained (estimated on that composite)
    own = run.renderer
    composite = composite_renderer(own, run.source.renderer, [(own.field, 1.0, region)], cameras,
                                   share_occupancy=True)
    return replace(run, renderer=composite, region=region, own=own)


def read_config(path: Path) -> RunConfig:
    """A run folder's ``config.yaml``, in the current settings layout (a folder of an earlier layout migrates:
    :func:`~nerfart_plugin.config.migrate.to_current`), validated. Raises NerfArtError naming the file when it is
    not a readable config."""
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise NerfArtError(f"{path} cannot be read as a run's config ({type(exc).__name__}: {exc}). It is written "
                           "when the run starts: run the command that made this run again, or restore the file.") from None
    if not isinstance(data, dict) or not data:
        raise NerfArtError(f"{path} holds no settings (it is empty or not a mapping). Run the command that made this "
                           "run again, or restore the file.")
    try:
        return parse_config(to_current(data))[0]
    except ConfigError as exc:
        raise NerfArtError(f"{path} is not a valid run config: {exc}. Run the command that made this run again, or "
                           "restore the file.") from None
