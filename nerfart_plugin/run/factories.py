"""The public seam: build what a run is made of from its config (a finished run opens with
:func:`nerfart_plugin.api.open_run`).

The stages (:mod:`nerfart_plugin.run.stages`), the benchmarks, the notebook and the tests all
build through these, so none of them re-wires the pieces::

    cfg = load_config(["stage=reconstruct", "backbone=nerf"])   # compose conf/ (Hydra)
    scene = build_scene(cfg)                                     # validated config + loaded scene + setup
    system = build_reconstruction_system(scene)                  # a LightningModule
    train_steps(system, 100, scene.device)                       # nerfart_plugin.run.fit
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Optional, Sequence

import torch

from nerfart_plugin.cameras.capture import CaptureCameras
from nerfart_plugin.config.schema import RunConfig
from nerfart_plugin.config.validate import parse_config
from nerfart_plugin.data.datamodule import datamodule_of
from nerfart_plugin.data.rays import views_at_resolution
from nerfart_plugin.data.scene import Scene
from nerfart_plugin.data.setup import SceneSetup, decide_setup
from nerfart_plugin.fields import occupancy_scores_opacity
from nerfart_plugin.fields.compiled import MIN_COMPILED_STEPS, apply_compile
from nerfart_plugin.guidance import default_negative_threshold
from nerfart_plugin.guidance.style import Style, build_style
from nerfart_plugin.fields.composite import RegionMask
from nerfart_plugin.regions.region import Region, region_from_config
from nerfart_plugin.results.run import Run
from nerfart_plugin.systems.base import build_renderer
from nerfart_plugin.systems.checkpoints import META_KEY, check_fits, checkpoint_meta, load_checkpoint, prefixed_state
from nerfart_plugin.systems.reconstruction import ReconstructionSystem
from nerfart_plugin.systems.stylization import StylizationSystem
from nerfart_plugin.utils.device import pick_device
from nerfart_plugin.utils.io import check_writable_dir

log = logging.getLogger("nerfart_plugin")

SOURCE_FIX = ("Pass source_checkpoint= the final.ckpt of a reconstruction made with this backbone and encoding, or "
              "leave it out to use (or make) the cached reconstruction of these settings.")


# ---------------------------------------------------------------------- the scene
@dataclass
class SceneContext:
    """A run's validated config with its loaded scene: what every stage builds on.

    Attributes:
        cfg: the typed config.
        plain: the same config as plain data (what run folders record in ``config.yaml``).
        dm: the scene's datamodule (``train_rays``, ``view_batch``, ``val_dataloader``).
        setup: the scene setup decided from the scene and ``cfg.render``.
        device: the compute device; root: the output root.
    """

    cfg: RunConfig
    plain: dict
    dm: Any
    setup: SceneSetup
    device: torch.device
    root: Path
    notes: list[str] = field(default_factory=list)

    @property
    def scene(self) -> Scene:
        return self.dm.load()

    @property
    def ndc(self) -> bool:
        return self.dm.ndc

    @property
    def cameras(self):
        """The capture's cameras (:class:`~nerfart_plugin.cameras.capture.CaptureCameras`)."""

        return CaptureCameras.from_scene(self.scene, self.ndc)

    def views(self, ids: Sequence[int], resolution: int) -> list[dict[str, Any]]:
        """Ray batches of views ``ids`` at ``resolution`` px on the long side (stylization, evaluation)."""

        return views_at_resolution(self.scene, list(ids), int(resolution), self.ndc)

    def with_config(self, cfg: Any) -> "SceneContext":
        """The same loaded scene under another config of the same data (the setup decided again)."""
        
        run, plain = parse_config(cfg)
        return replace(self, cfg=run, plain=plain, setup=scene_setup(self.scene, run, self.ndc))


def build_scene(cfg: Any) -> SceneContext:
    """Validate ``cfg`` (a DictConfig, dict or RunConfig), load its scene and decide the scene setup."""

    run, plain = parse_config(cfg)
    root = check_writable_dir(run.output_root, "output_root")
    dm = datamodule_of(run, root / "cache")  # loaders' caches (selfie frames + SfM)
    scene = dm.load()
    for note in scene.notes:
        log.info("data: %s", note)
    return SceneContext(run, plain, dm, scene_setup(scene, run, dm.ndc), pick_device(run.device), root,
                        list(scene.notes))


def scene_setup(scene: Scene, cfg: RunConfig, ndc: bool) -> SceneSetup:
    """What the scene requires of a run of ``cfg`` (:func:`~nerfart_plugin.data.setup.decide_setup`)."""
    return decide_setup(scene, cfg.render, ndc=ndc, opacity_scores=occupancy_scores_opacity(cfg.backbone),
                        encoding_cfg=cfg.encoding, reconstruct_cfg=cfg.reconstruct)


# ---------------------------------------------------------------------- renderers and systems
def build_reconstruction_system(scene: SceneContext, out_dir: Optional[Path] = None, setup: Optional[SceneSetup] = None):
    """The reconstruction LightningModule of ``scene.cfg`` on the scene's training rays."""

    scene.dm.setup("fit")
    c = scene.cfg
    system = ReconstructionSystem(c, setup or scene.setup, train_rays=scene.dm.train_rays,
                                  out_dir=str(out_dir) if out_dir is not None else None)
    return compile_system(system, scene, c.reconstruct.steps, "reconstruction")


def load_renderer_state(ckpt_path: Path, scene: Optional[SceneContext] = None) -> dict[str, torch.Tensor]:
    """The renderer tensors of a reconstruction / stylization checkpoint, read without running code; with
    ``scene``, checked to fit its backbone / encoding / setup (the error names the file and what differs)."""
    ckpt = load_checkpoint(ckpt_path, fix=SOURCE_FIX)
    state = prefixed_state(ckpt, "renderer.")
    if scene is not None:
        c = scene.cfg
        here = checkpoint_meta("reconstruct", c.backbone, c.encoding, scene.setup)
        check_fits(build_renderer(c, scene.setup), state, ckpt_path, ckpt.get(META_KEY), here, SOURCE_FIX)
    return state


def stylize_settings(scene: SceneContext, style: Optional[Style] = None):
    """The ``stylize`` section with its ``auto`` settings and ``epochs`` resolved: ``resolution`` (the loaded
    images' long side: the data resolution policy, 256x256 head, 270x480 selfies), ``steps`` (epochs x training
    views) and, given the ``style``, ``negative_threshold`` (the guide's own)."""

    sc = scene.cfg.stylize
    update: dict[str, Any] = {}
    if sc.resolution == "auto":
        update["resolution"] = max(scene.scene.height, scene.scene.width)
    if sc.epochs:
        update["steps"] = int(sc.epochs) * len(scene.scene.train_ids)
    if style is not None and sc.negative_threshold == "auto":
        update["negative_threshold"] = default_negative_threshold(style.guidance)
    return sc.model_copy(update=update)


def bound_region(scene: SceneContext, region: Optional[Region]) -> Optional[RegionMask]:
    """``region`` bound to the scene's field (its frame and box, on ``region.resolution`` cells a side)."""
    if region is None:
        return None
    return region.bind(scene.cameras.field_to_world, scene.setup.bound, scene.cfg.region.resolution)


def build_stylization_system(scene: SceneContext, source_state: dict, style: Optional[Style] = None,
                             out_dir: Optional[Path] = None):
    """The stylization LightningModule of ``scene.cfg`` starting from ``source_state`` (the reconstruction's
    renderer tensors, :func:`load_renderer_state`); ``style``: from :func:`build_style` by default."""

    c = scene.cfg
    style = style or build_style(c)
    sc = stylize_settings(scene, style)
    views = scene.views(scene.scene.train_ids, sc.resolution)
    system = StylizationSystem(c, scene.setup, style, source_state, views, settings=sc,
                               out_dir=str(out_dir) if out_dir is not None else None,
                               region=bound_region(scene, region_from_config(c.region)))
    return compile_system(system, scene, sc.steps, "stylization")


def compile_system(system: Any, scene: SceneContext, steps: int, stage: str) -> Any:
    """``system`` with its fields compiled where the ``compile`` setting says so for a ``stage`` (reconstruction |
    stylization) of ``steps`` steps (:func:`~nerfart_plugin.fields.compiled.apply_compile`); what was decided is
    ``system.compile_choice``, recorded in the run's ``metrics.json``."""
    system.compile_choice = apply_compile(system, scene.cfg.compile, torch.device(scene.device), steps,
                                          MIN_COMPILED_STEPS[stage])
    log.info("compile: %s", system.compile_choice)
    return system


def checkpoint_run(ckpt: Path, scene: SceneContext) -> Run:
    """A reconstruction checkpoint read as a :class:`~nerfart_plugin.results.run.Run` of ``scene``'s settings
    (``stage=export source_checkpoint=...``): read without running code and checked to fit them
    (:func:`load_renderer_state`), so a checkpoint of other settings is named with what differs."""
    renderer = build_renderer(scene.cfg, scene.setup)
    renderer.load_state_dict(load_renderer_state(ckpt, scene))
    return Run(ckpt.parent, ckpt, "reconstruction", scene.cfg, {}, renderer.to(scene.device).eval(), scene.cameras,
               scene.device)
