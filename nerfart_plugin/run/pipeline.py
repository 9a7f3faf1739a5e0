"""Run the stages a config asks for: reconstruct -> stylize, export, render.

The pieces live where their concern is:

* :mod:`nerfart_plugin.config.schema`: every setting, its default and its check (validated here first);
* :mod:`nerfart_plugin.run.factories`: the scene, the systems, the guidance, finished runs (public);
* :mod:`nerfart_plugin.run.stages`: one object per stage (key, run folder, system, outputs);
* :mod:`nerfart_plugin.run.folders`: run folders, reuse / resume policy, locks;
* :mod:`nerfart_plugin.run.fit`: the one fit skeleton (checkpoints, Ctrl-C, resume, OOM);
* :mod:`nerfart_plugin.objectives.evaluation`: every metric.

Reliability: the config is validated before anything is loaded, the output root must be
writable, each run folder is locked while a stage works in it (``lock_timeout``), Ctrl-C
stops at a step boundary with a checkpoint (exit code 130), and checkpoints are read without
running code and checked against the model (:mod:`nerfart_plugin.systems.checkpoints`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import lightning as L
import torch
from omegaconf import DictConfig

from nerfart_plugin.config.issues import show
from nerfart_plugin.config.schema import RunConfig
from nerfart_plugin.config.validate import parse_config
from nerfart_plugin.errors import ConfigError, NerfArtError, RunInterrupted
from nerfart_plugin.guidance import validate_prompt
from nerfart_plugin.guidance.style import Style, build_style, check_style
from nerfart_plugin.guidance.style_image import read_style_image
from nerfart_plugin.run.factories import SceneContext, build_scene
from nerfart_plugin.run.stages.base import LiveViewerFactory
from nerfart_plugin.run.stages.export import ExportStage
from nerfart_plugin.run.stages.preview import PreviewStage
from nerfart_plugin.run.stages.reconstruct import ReconstructStage
from nerfart_plugin.run.stages.render import RenderStage
from nerfart_plugin.run.stages.stylize import StylizeStage, stylization_source
from nerfart_plugin.utils.device import pick_device
from nerfart_plugin.utils.io import atomic_write_json, check_writable_dir

log = logging.getLogger("nerfart_plugin")


def check_stage(c: RunConfig) -> None:
    """The checks that depend on the stage, after the config's own (:func:`~nerfart_plugin.config.validate.parse_config`):
    multi-device only for the reconstruction, a prompt for stylization, an existing ``source_checkpoint``, an
    available ``device``."""
    tc = c.trainer
    plan = PLANS[c.stage]
    if (tc.strategy != "auto" or tc.num_nodes != 1 or tc.devices != 1) and not plan.multi_device:
        raise ConfigError("Multi-device training (trainer.strategy/devices/num_nodes) is supported for "
                          "stage=reconstruct only: the stylization stage optimizes one view per step with several "
                          "backward passes (Section 4.4) on one device. Run stage=reconstruct with DDP, then "
                          "stage=stylize with trainer.strategy=auto trainer.devices=1 trainer.num_nodes=1 "
                          "source_checkpoint=<the DDP run>/final.ckpt.")
    if plan.needs_prompt:
        if c.prompt is None and not c.style_image.given:
            raise ConfigError(f"stage={c.stage} needs a style: add +prompt=\"Vincent van Gogh\" or "
                              "+style_image=<picture.png> (or both; or stage=reconstruct).")
        if c.prompt is not None:
            validate_prompt(c.prompt)
        if c.style_image.given:
            read_style_image(c.style_image.file)  # a bad picture stops the run before any work
    if c.source_checkpoint and not Path(c.source_checkpoint).expanduser().is_file():
        raise ConfigError(f"source_checkpoint={c.source_checkpoint}: no such file. Point it at the final.ckpt of a "
                          "reconstruction (outputs/reconstructions/<run>/final.ckpt) or leave it out to use the "
                          "cached one.")
    check_device(c.device, tc.devices)


def check_device(device: str, devices: Any = 1) -> None:
    """ConfigError if ``device`` names an accelerator this machine does not have, or ``trainer.devices``
    is a GPU-only form (-1, a list of ids) for a CPU / MPS run."""
    if device.startswith("cuda"):
        n = torch.cuda.device_count() if torch.cuda.is_available() else 0
        index = int(device.split(":", 1)[1]) if ":" in device else 0
        if index >= n:
            raise ConfigError(f"device={device}: this machine has {n} CUDA device(s) (torch.cuda.device_count()); "
                              "use device=auto (the best available) or device=cpu.")
    if device == "mps" and not torch.backends.mps.is_available():
        raise ConfigError("device=mps: Apple's Metal backend is not available here; use device=auto or device=cpu.")
    kind = pick_device(device).type
    if kind != "cuda" and not (devices == "auto" or (isinstance(devices, int) and devices >= 1)):
        raise ConfigError(f"trainer.devices={show(devices)}: on {kind} give a number of processes N >= 1 (or auto); "
                          "-1 and lists of device ids select GPUs (device=cuda).")


class Pipeline:
    """One configured job: validates the config, loads the scene once and runs the requested stages.

    Attributes:
        cfg: the typed config; plain: the same as plain data.
        results: what ``run`` returns (per stage: its folder and headline metrics).
        scene_context: the loaded scene (after :meth:`load_data`).
    """

    def __init__(self, cfg: DictConfig | dict, live: Optional[LiveViewerFactory] = None) -> None:
        self.cfg, self.plain = parse_config(cfg)
        check_stage(self.cfg)
        self.live = live
        self.root = check_writable_dir(self.cfg.output_root, "output_root")
        self.results: dict[str, Any] = {"stage": self.cfg.stage}
        self.style: Optional[Style] = None
        self.scene_context: Optional[SceneContext] = None
        self.recon: Optional[ReconstructStage] = None

    # ------------------------------------------------------------------ what the stages share
    def prepare_guidance(self) -> None:
        """Build CLIP/VGG (or toy) and resolve the prompt and the negatives first, so missing weights, a prompt
        the guide cannot take and a missing negatives file fail before any training."""
        self.style = build_style(self.cfg)
        check_style(self.style, self.cfg.stylize.negatives)

    def load_data(self) -> None:
        """Load the scene and decide its setup; the reconstruction's run folder follows from them."""
        self.scene_context = build_scene(self.cfg)
        self.recon = ReconstructStage(self.scene_context, self.live)

    @property
    def scene(self):
        return self._loaded().scene

    @property
    def recon_dir(self) -> Path:
        """The run folder of the reconstruction of this data + backbone + settings."""
        self._loaded()
        return self.recon.folder.path

    def _loaded(self) -> SceneContext:
        if self.scene_context is None:
            raise NerfArtError("Pipeline.load_data() has not run: the scene is not loaded yet.")
        return self.scene_context

    # ------------------------------------------------------------------ stages
    def reconstruct(self) -> Path:
        """Stage 1 (a finished reconstruction is reused); returns its ``final.ckpt``."""
        self._loaded()
        result = self.recon.run()
        self.results["reconstruction"] = result.summary
        return result.checkpoint

    def stylize(self, stage: type[StylizeStage] = StylizeStage, name: str = "stylization") -> Path:
        """Stage 2 (a finished stylization is not redone); returns its ``final.ckpt``."""
        source, source_keys = stylization_source(self._loaded(), self.recon)
        if not self.cfg.source_checkpoint and "reconstruction" not in self.results:  # not verified by this run yet
            self.recon.folder.set_aside_if_damaged()
        if not source.exists():
            raise NerfArtError(f"No reconstruction at {source} for this data + backbone + settings. Run "
                               "stage=reconstruct (or stage=all) first, or pass source_checkpoint=/path/final.ckpt.")
        result = stage(self.scene_context, self.style, source, source_keys, self.live).run()
        self.results[name] = result.summary
        return result.checkpoint

    def preview(self) -> Path:
        """``stage=preview``: a short low-resolution stylization (:class:`~nerfart_plugin.run.stages.preview.PreviewStage`)."""
        return self.stylize(PreviewStage, "preview")

    def export(self) -> None:
        """``stage=export``: meshes from ``source_checkpoint`` (or the cached reconstruction)."""
        ckpt = Path(self.cfg.source_checkpoint) if self.cfg.source_checkpoint else self.recon_dir / "final.ckpt"
        self.results["export"] = ExportStage(self.cfg, ckpt, self._loaded()).run().summary

    def render(self) -> None:
        """``stage=render``: videos of ``render.run``, else of this config's finished stylization (with a style)
        or reconstruction."""
        if self.cfg.mix.runs:
            run_dir = None
        else:
            run_dir = Path(self.cfg.render.run).expanduser() if self.cfg.render.run else self.finished_run_dir()
        self.results["render"] = RenderStage(self.cfg, run_dir).run().summary

    def finished_run_dir(self) -> Path:
        """The finished stylization (with a style) or reconstruction of this config, for ``stage=render``."""
        if not _styled(self.cfg):
            folder, what = self.recon.folder, "reconstruction"
        else:
            source, source_keys = stylization_source(self._loaded(), self.recon)
            folder, what = StylizeStage(self.scene_context, self.style, source, source_keys).folder, "stylization"
        if not folder.finished:
            raise NerfArtError(f"stage=render: the {what} of these settings has not finished ({folder.path} has no "
                               "final.ckpt). Run it first (stage=all, the same settings), or point render.run= at a "
                               "run folder.")
        return folder.path

    # ------------------------------------------------------------------ run
    def run(self) -> dict[str, Any]:
        """Run the configured stages.

        Raises:
            RunInterrupted: Ctrl-C, at any point (the message says how to resume).
        """
        try:
            return self._run()
        except KeyboardInterrupt:  # outside training (loading, COLMAP, evaluation, export)
            raise RunInterrupted("interrupted; nothing finished is lost: run the same command again to continue "
                                 "(finished stages are reused, a stage in progress resumes from its last.ckpt)") from None

    def _run(self) -> dict[str, Any]:
        plan = PLANS[self.cfg.stage]
        L.seed_everything(self.cfg.seed, workers=True, verbose=False)
        if plan.guidance(self.cfg):
            self.prepare_guidance()
        if plan.data(self.cfg):
            self.load_data()
        for step in plan.steps:
            step(self)
        return self.results

    # ------------------------------------------------------------------ the steps of the plans
    def reconstruct_unless_given(self) -> None:
        """Stage 1, unless ``source_checkpoint`` names the reconstruction to start from."""
        if self.cfg.source_checkpoint:
            return
        if self.cfg.stage == "preview" and not self.recon.folder.finished:
            log.warning("a preview starts from the reconstruction of this capture, which is not made yet: it is "
                        "trained first (once; every later preview and stylization reuses it), then the preview "
                        "follows in about a minute")
        self.reconstruct()

    def export_meshes(self) -> None:
        """``stage=export``: of ``mix.runs`` when given (no data needed), else :meth:`export`."""
        if self.cfg.mix.runs:
            self.results["export"] = ExportStage(self.cfg, None).run().summary
        else:
            self.export()


def _always(c: RunConfig) -> bool:
    return True


def _never(c: RunConfig) -> bool:
    return False


def _runs_given(c: RunConfig) -> bool:
    return bool(c.render.run or c.mix.runs)


def _styled(c: RunConfig) -> bool:
    """A style is given (a prompt, a style picture or both): the config names a stylization."""
    return c.prompt is not None or c.style_image.given


@dataclass(frozen=True)
class StagePlan:
    """What one value of ``stage=`` does: whether the guide (prompt, negatives) and the capture are loaded first
    (functions of the config), then the pipeline's steps in order.

    Attributes:
        needs_prompt: the stage stylizes, so ``prompt`` is required (checked before anything loads).
        multi_device: the stage may train on several devices (``trainer.strategy`` / ``devices`` / ``num_nodes``).
    """

    steps: tuple[Callable[["Pipeline"], Any], ...]
    guidance: Callable[[RunConfig], bool] = _never
    data: Callable[[RunConfig], bool] = _always
    needs_prompt: bool = False
    multi_device: bool = False


#: ``stage=`` -> its plan (the schema's ``stage`` choices, one entry each)
PLANS: dict[str, StagePlan] = {
    "reconstruct": StagePlan((Pipeline.reconstruct_unless_given,), multi_device=True),
    "stylize": StagePlan((Pipeline.stylize,), guidance=_always, needs_prompt=True),
    "all": StagePlan((Pipeline.reconstruct_unless_given, Pipeline.stylize), guidance=_always, needs_prompt=True),
    "preview": StagePlan((Pipeline.reconstruct_unless_given, Pipeline.preview), guidance=_always, needs_prompt=True),
    # a given run (render.run, mix.runs) needs neither data nor guide; else this config's run, found by its key
    "render": StagePlan((Pipeline.render,), guidance=lambda c: _styled(c) and not _runs_given(c),
                        data=lambda c: not _runs_given(c)),
    "export": StagePlan((Pipeline.export_meshes,), data=lambda c: not c.mix.runs),
}


def run(cfg: DictConfig | dict, output_dir: Optional[Path] = None,
        live: Optional[LiveViewerFactory] = None) -> dict[str, Any]:
    """Entry point used by ``python -m nerfart_plugin``: runs the pipeline and writes ``result.json``
    into ``output_dir`` (the Hydra job folder; None: nowhere)."""
    results = Pipeline(cfg, live).run()
    if output_dir is not None:
        atomic_write_json(Path(output_dir) / "result.json", results)
    return results
