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
from omegaconf import DictConfig

from nerfart_plugin.systems.checkpoints import META_KEY, check_fits, checkpoint_meta, load_checkpoint, prefixed_state
from nerfart_plugin.data.scene import Scene
from nerfart_plugin.config.schema import RunConfig, parse_config
from nerfart_plugin.data.setup import SceneSetup

log = logging.getLogger("nerfart_plugin")

SOURCE_FIX = ("Pass source_checkpoint= the final.ckpt of a reconstruction made with this backbone and encoding, or "
              "leave it out to use (or make) the cached reconstruction of these settings.")


def load_config(overrides: Sequence[str] = ()) -> DictConfig:
    """``conf/config.yaml`` (on the schema's defaults) composed with Hydra ``overrides``, as the CLI does."""
    from hydra import compose, initialize_config_dir

    from nerfart_plugin.config.compose import config_dir

    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def typed(cfg: Any) -> tuple[RunConfig, dict]:
    """``(RunConfig, plain dict)`` of a config: a RunConfig as it is, anything else validated."""
    if isinstance(cfg, RunConfig):
        return cfg, cfg.model_dump(mode="json")
    return parse_config(cfg)


# ---------------------------------------------------------------------- the scene
@dataclass
class SceneContext:
    """A run's validated config with its loaded scene: what every stage builds on.

    Attributes:
        cfg: the typed config (component sections are dicts).
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
        from nerfart_plugin.cameras.capture import CaptureCameras

        return CaptureCameras.from_scene(self.scene, self.ndc)

    def views(self, ids: Sequence[int], resolution: int) -> list[dict[str, Any]]:
        """Ray batches of views ``ids`` at ``resolution`` px on the long side (stylization, evaluation)."""
        from nerfart_plugin.data.rays import views_at_resolution

        return views_at_resolution(self.scene, list(ids), int(resolution), self.ndc)

    def with_config(self, cfg: Any) -> "SceneContext":
        """The same loaded scene under another config of the same data (the setup decided again)."""
        from nerfart_plugin.fields import occupancy_scores_opacity
        from nerfart_plugin.data.setup import decide_setup

        run, plain = typed(cfg)
        return replace(self, cfg=run, plain=plain, setup=decide_setup(self.scene, run.render, ndc=self.ndc,
                                                                      opacity_scores=occupancy_scores_opacity(run.backbone),
                                                                      encoding_cfg=run.encoding,
                                                                      reconstruct_cfg=run.reconstruct))


def build_scene(cfg: Any) -> SceneContext:
    """Validate ``cfg`` (a DictConfig, dict or RunConfig), load its scene and decide the scene setup."""
    from nerfart_plugin.data.datamodule import SceneDataModule
    from nerfart_plugin.fields import occupancy_scores_opacity
    from nerfart_plugin.data.setup import decide_setup
    from nerfart_plugin.utils.device import pick_device
    from nerfart_plugin.utils.io import check_writable_dir

    run, plain = typed(cfg)
    root = check_writable_dir(run.output_root, "output_root")
    dm = SceneDataModule({"background_color": run.render.background_color, **run.data,
                          "cache_root": str(root / "cache")})  # loaders' caches (selfie frames + SfM)
    scene = dm.load()
    for note in scene.notes:
        log.info("data: %s", note)
    setup = decide_setup(scene, run.render, ndc=dm.ndc, opacity_scores=occupancy_scores_opacity(run.backbone),
                         encoding_cfg=run.encoding, reconstruct_cfg=run.reconstruct)
    return SceneContext(run, plain, dm, setup, pick_device(run.device), root, list(scene.notes))


# ---------------------------------------------------------------------- renderers and systems
def build_renderer(cfg: RunConfig, setup: SceneSetup):
    """The renderer (field + background + occupancy grid) of ``cfg``'s backbone / encoding / render settings."""
    from nerfart_plugin.systems.base import build_renderer as _build

    return _build(cfg.backbone, cfg.encoding, cfg.render, setup)


def build_reconstruction_system(scene: SceneContext, out_dir: Optional[Path] = None, setup: Optional[SceneSetup] = None):
    """The reconstruction LightningModule of ``scene.cfg`` on the scene's training rays."""
    from nerfart_plugin.systems.reconstruction import ReconstructionSystem

    scene.dm.setup("fit")
    c = scene.cfg
    return ReconstructionSystem(c.reconstruct, c.backbone, c.encoding, c.render, setup or scene.setup,
                                train_rays=scene.dm.train_rays, seed=c.seed,
                                out_dir=str(out_dir) if out_dir is not None else None)


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


@dataclass
class Style:
    """The guidance of a stylization and the prompts it is given.

    Attributes:
        guidance / perceptual: the frozen encoders (CLIP + VGG, toy, imagenet).
        real: both are real pretrained models (else the outputs are stamped).
        stamp: suffix of every output file ("" for real CLIP; ``_UNSTYLED-toy``, ``_VERIFY-imagenet``).
        raw_prompt / prompt: the prompt as typed / after augmentation; source_prompt: Eq. 4's t_src.
        negatives: ``(stylize.negatives, the resolved negative prompts)`` once :func:`check_style` resolved
            them, so the stylization does not resolve them again; None before.
    """

    guidance: Any
    perceptual: Any
    real: bool
    stamp: str
    raw_prompt: str
    prompt: str
    source_prompt: str
    negatives: Optional[tuple[str, list]] = None

    @property
    def warning(self) -> Optional[str]:
        """The ``WARNING`` of a stylization's ``metrics.json`` when the guide is not a real CLIP (None when it is)."""
        if self.stamp.startswith("_VERIFY"):
            return ("VERIFICATION run: guided by an ImageNet classifier standing in for CLIP, not by CLIP; see the "
                    "judge block")
        if not self.real:
            return "UNSTYLED by a real model: random or toy guidance weights were used"
        return None


def build_style(cfg: Any, guidance: Any = None, perceptual: Any = None) -> Style:
    """Build the guidance of ``cfg`` (first, so missing weights fail before any training) and resolve the
    prompts: augmentation (``prompt_augment``), ``source_prompt=auto`` from ``data.subject``."""
    from nerfart_plugin.guidance import (augment_prompt, build_guidance, build_perceptual, default_source_prompt,
                                         validate_prompt)

    c, _ = typed(cfg)
    g = c.guidance
    guidance = guidance if guidance is not None else build_guidance(g)
    perceptual = perceptual if perceptual is not None else build_perceptual(g)
    real = bool(guidance.is_real and getattr(perceptual, "is_real", True))
    stamp = guidance.output_stamp() or ("" if real else f"_UNSTYLED-{g['name']}")
    if not real:
        log.warning("guidance is not a real pretrained CLIP (%s): every output is stamped %r", g["name"], stamp)
    raw = validate_prompt(c.prompt)
    prompt = augment_prompt(raw) if c.prompt_augment else raw
    if prompt != raw:
        log.info("prompt augmented: %r -> %r", raw, prompt)
    src = c.source_prompt if c.source_prompt != "auto" else default_source_prompt(c.data.get("subject") or "object")
    return Style(guidance, perceptual, real, stamp, raw, prompt, src)


def check_style(style: Style, negatives: str) -> None:
    """What stylization will resolve, resolved now, before any training: the prompts in the guide's terms
    (``guidance=imagenet`` needs an ImageNet class) and the negative prompts (``stylize.negatives``: a
    file must exist and parse). Raises the ConfigError the stylization would raise later."""
    from nerfart_plugin.guidance import resolve_negatives

    with torch.no_grad():
        style.guidance.encode_text([style.prompt])
    style.negatives = (negatives, resolve_negatives(negatives, style.guidance, style.prompt))


def negatives_of(style: Style, spec: str) -> list:
    """The negative prompts ``spec`` (``stylize.negatives``) names for ``style``: as :func:`check_style` resolved
    them when it did so for the same spec, else resolved now."""
    from nerfart_plugin.guidance import resolve_negatives

    if style.negatives is not None and style.negatives[0] == spec:
        return style.negatives[1]
    return resolve_negatives(spec, style.guidance, style.prompt)


def stylize_settings(scene: SceneContext, style: Optional[Style] = None):
    """The ``stylize`` section with its ``auto`` settings and ``epochs`` resolved: ``resolution`` (the loaded
    images' long side: the data resolution policy, 256x256 head, 270x480 selfies), ``steps`` (epochs x training
    views) and, given the ``style``, ``negative_threshold`` (the guide's own)."""
    from nerfart_plugin.guidance import default_negative_threshold

    sc = scene.cfg.stylize
    update: dict[str, Any] = {}
    if sc.resolution == "auto":
        update["resolution"] = max(scene.scene.height, scene.scene.width)
    if sc.epochs:
        update["steps"] = int(sc.epochs) * len(scene.scene.train_ids)
    if style is not None and sc.negative_threshold == "auto":
        update["negative_threshold"] = default_negative_threshold(style.guidance)
    return sc.model_copy(update=update)


def style_choices(style: Style, settings: Any) -> dict[str, Any]:
    """What the style's ``auto`` settings became (:mod:`nerfart_plugin.config.auto`): the source prompt, the view size,
    the negatives (where they came from and how many) and the threshold that excludes near-synonyms."""
    from nerfart_plugin.guidance import negatives_origin

    spec = settings.negatives
    return {"source_prompt": style.source_prompt, "stylize.resolution": settings.resolution,
            "stylize.negatives": f"{negatives_origin(spec, style.guidance)}: {len(negatives_of(style, spec))} prompts",
            "stylize.negative_threshold": settings.negative_threshold}


def build_stylization_system(scene: SceneContext, source_state: dict, style: Optional[Style] = None,
                             out_dir: Optional[Path] = None):
    """The stylization LightningModule of ``scene.cfg`` starting from ``source_state`` (the reconstruction's
    renderer tensors, :func:`load_renderer_state`); ``style``: from :func:`build_style` by default."""
    from nerfart_plugin.systems.stylization import StylizationSystem

    c = scene.cfg
    style = style or build_style(c)
    sc = stylize_settings(scene, style)
    views = scene.views(scene.scene.train_ids, sc.resolution)
    return StylizationSystem(cfg=sc, experiment=c.experiment, backbone_cfg=c.backbone, encoding_cfg=c.encoding,
                             render_cfg=c.render, setup=scene.setup, source_state=source_state, views=views,
                             guidance=style.guidance, perceptual=style.perceptual, prompt=style.prompt,
                             source_prompt=style.source_prompt, negatives=negatives_of(style, sc.negatives), seed=c.seed,
                             out_dir=str(out_dir) if out_dir is not None else None, stamp=style.stamp,
                             raw_prompt=style.raw_prompt)


# ---------------------------------------------------------------------- finished runs

