"""The skeleton both training stages share (:class:`TrainingStage`): reuse a finished run, else lock the folder,
prepare it, build the system, fit (resume, atomic checkpoints, Ctrl-C, OOM), write the outputs and
``metrics.json`` on rank 0, then ``final.ckpt``; and what every stage returns (:class:`StageResult`)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from nerfart_plugin.cameras.capture import CaptureCameras, viewer_cameras
from nerfart_plugin.config.auto import component_choices, recorded
from nerfart_plugin.config.schema import ViewerConfig
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.regions.region import region_from_config
from nerfart_plugin.results.record import RunRecord, key_in_name
from nerfart_plugin.results.run import Run, mix, open_run
from nerfart_plugin.run.factories import SceneContext
from nerfart_plugin.run.fit import FitResult, publish_final, stage_final
from nerfart_plugin.run.folders import RunFolder
from nerfart_plugin.utils.clock import PartClock
from nerfart_plugin.utils.io import atomic_write_json

log = logging.getLogger("nerfart_plugin")




@dataclass
class StageResult:
    """What a stage leaves: its checkpoint and the summary that goes into the run's ``result.json``."""

    checkpoint: Path
    summary: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class LiveTarget:
    """What a live viewer of a training stage is handed (``viewer.live``).

    Attributes:
        cameras: the capture's cameras; photos: its images [N,H,W,3] (floats in [0,1]).
        folder: the run folder; title: what trains there ("reconstruction", "stylization").
        settings: the ``viewer`` section; chunk: rays per no-grad chunk of the frames it renders.
    """

    cameras: CaptureCameras
    photos: np.ndarray
    folder: Path
    title: str
    settings: ViewerConfig
    chunk: int


#: builds the Lightning callback that shows a training stage live; handed in by the entry point that has a viewer
LiveViewerFactory = Callable[[LiveTarget], Any]


class TrainingStage:
    """The skeleton both training stages share; subclasses say what is trained and what is written.

    Args:
        scene: the run's config and loaded scene; live: the live viewer's factory (``viewer.live``), if any.
    """

    folder: RunFolder

    def __init__(self, scene: SceneContext, live: Optional[LiveViewerFactory] = None) -> None:
        self.scene = scene
        self.live = live
        self.clock = PartClock()  # stage_seconds in metrics.json: where the time went

    def run(self) -> StageResult:
        """Reuse the finished run, or compute it holding the folder's lock."""
        return self.folder.reuse_or_run(self.scene.cfg.lock_timeout, self.compute, self.reuse)

    def reuse(self) -> StageResult:
        log.info(self.reused_message, self.folder.path)
        return StageResult(self.folder.final, {"dir": str(self.folder.path)})

    def compute(self) -> StageResult:
        self.check_inputs()  # a wrong input stops before the run folder exists
        self.folder.prepare(self.scene.cfg.resume, self.scene.plain)
        system = self.build_system()
        fit = self.fit(system)
        staged = stage_final(fit, self.folder)  # every rank (a collective under DDP)
        if staged is None:  # DDP: evaluation and outputs on rank 0 only
            return StageResult(self.folder.final)
        self.clock.seconds["fit"] = round(fit.seconds, 3)
        metrics = self.outputs(system, fit)
        metrics["auto"] = recorded(self.scene.cfg, self.auto_choices(system, fit))
        metrics["stage_seconds"] = self.clock.seconds
        write_cameras(self.scene, self.folder.path)
        atomic_write_json(self.folder.path / "metrics.json", metrics)
        self.record().write(self.folder.path)
        publish_final(staged, self.folder)
        return StageResult(self.folder.final, {"dir": str(self.folder.path), **self.summary(metrics)})

    # ---- what a stage says
    reused_message = "reusing %s"
    #: what the record says made the run (``run.json``'s ``kind`` and ``stage``)
    kind, stage = "reconstruction", "reconstruct"

    def record(self) -> RunRecord:
        """The run's ``run.json`` (:mod:`nerfart_plugin.results.record`)."""
        return RunRecord.new(self.kind, self.stage, key_in_name(self.folder.path.name), self.folder.path, self.source_run)

    @property
    def source_run(self) -> Optional[Path]:
        """The run folder this one starts from (None for a reconstruction)."""
        return None

    def check_inputs(self) -> None:
        """Read and check what the stage starts from (nothing by default)."""

    def live_callbacks(self) -> list[Any]:
        """The live viewer on the field being trained, when ``viewer.live``: the callback the stage was handed
        (``live``, built by the viewer: :func:`nerfart_plugin.viewer.live.live_viewer`)."""
        vc = self.scene.cfg.viewer
        if not vc.live:
            return []
        if self.live is None:
            raise ConfigError("viewer.live=true needs the live viewer, which the command line hands in: run "
                              "python -m nerfart_plugin ... viewer.live=true, or in Python pass "
                              "live=nerfart_plugin.viewer.live.live_viewer to nerfart_plugin.run.pipeline.run.")
        scene = self.scene.scene
        return [self.live(LiveTarget(CaptureCameras.from_scene(scene, self.scene.ndc), scene.images.numpy(),
                                     self.folder.path, self.folder.what, vc, self.scene.cfg.render.chunk))]

    def auto_choices(self, system: Any, fit: FitResult) -> dict[str, Any]:
        """What the run's ``auto`` settings became (:mod:`nerfart_plugin.config.auto`): the scene's, the data's, the
        compute's and the components' (the field, and for a stylization its guide and perceptual network)."""
        scene = self.scene.scene
        return {**self.scene.setup.auto_choices(), "data.resolution": max(scene.height, scene.width),
                "device": self.scene.device, "trainer.strategy": type(fit.trainer.strategy).__name__,
                "compile": getattr(system, "compile_choice", "off"),
                **component_choices(self.scene.device, [system.field, getattr(system, "guidance", None),
                                                        getattr(system, "perceptual", None)])}

    def build_system(self) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError

    def fit(self, system: Any) -> FitResult:  # pragma: no cover - abstract
        raise NotImplementedError

    def outputs(self, system: Any, fit: FitResult) -> dict[str, Any]:  # pragma: no cover - abstract
        raise NotImplementedError

    def summary(self, metrics: dict[str, Any]) -> dict[str, Any]:  # pragma: no cover - abstract
        raise NotImplementedError


def write_cameras(scene: SceneContext, folder: Path) -> None:
    """``cameras.json``: the capture's cameras in the frame of the run's meshes, for the viewer and
    ``stage=render`` (:meth:`~nerfart_plugin.cameras.capture.CaptureCameras.from_json`)."""

    atomic_write_json(folder / "cameras.json", viewer_cameras(scene.scene, scene.cfg.export.frame, scene.ndc))


def blended_run(cfg: Any, folder: Optional[Path]) -> Run:
    """The :class:`~nerfart_plugin.results.run.Run` that ``stage=render`` / ``stage=export`` work on: ``mix.runs``
    at ``mix.weights`` when given, else ``folder`` (a run folder or a checkpoint in one) at ``strength``; with a
    ``region``, each stylization inside it only (the source elsewhere)."""
    region = region_from_config(cfg.region)
    if cfg.mix.runs:
        runs = [open_run(Path(r).expanduser(), device=cfg.device) for r in cfg.mix.runs]
        return mix([r.with_region(region) for r in runs] if region is not None else runs, cfg.mix.weights)
    run = open_run(folder, device=cfg.device)
    if region is not None:
        run = run.with_region(region)
    return run if cfg.strength == 1.0 else run.with_strength(cfg.strength)
