"""``stage=reconstruct``: fit the field to the photos into ``reconstructions/<data>-<backbone>-<encoding>-<key>/``
(``final.ckpt``, ``metrics.json`` with held-out PSNR / SSIM and the scene setup, ``val/`` images,
``mesh/source.*``)."""

from __future__ import annotations

import logging
from typing import Any, Optional

from nerfart_plugin.export.run_meshes import export_source_mesh
from nerfart_plugin.objectives.evaluation import evaluate_views, evaluation_views
from nerfart_plugin.run.factories import SceneContext, build_reconstruction_system
from nerfart_plugin.run.fit import FitResult, fit_stage
from nerfart_plugin.run.folders import RunFolder
from nerfart_plugin.run.keys import reconstruction_keys
from nerfart_plugin.run.stages.base import LiveViewerFactory, TrainingStage
from nerfart_plugin.systems.callbacks import FiniteGradientGuard

log = logging.getLogger("nerfart_plugin")


class ReconstructStage(TrainingStage):
    """Stage 1: fit the field to the photos (:class:`~nerfart_plugin.systems.ReconstructionSystem`)."""

    reused_message = "reusing the cached reconstruction %s (same data, backbone and settings)"

    def __init__(self, scene: SceneContext, live: Optional[LiveViewerFactory] = None) -> None:
        super().__init__(scene, live)
        c = scene.cfg
        self.keys = reconstruction_keys(scene)
        self.names = [f"{c.data.name}-{c.backbone.name}-{c.encoding.name}-{key}" for key in self.keys.values()]
        self.folder = RunFolder.find(scene.root / "reconstructions", self.names, "reconstruction")

    def build_system(self) -> Any:
        return build_reconstruction_system(self.scene, out_dir=self.folder.path)

    def fit(self, system: Any) -> FitResult:
        rc = self.scene.cfg.reconstruct
        val_kw: dict[str, Any] = (dict(val_check_interval=rc.val_every, check_val_every_n_epoch=None,
                                       limit_val_batches=rc.val_views or 1.0)
                                  if rc.val_every > 0 else dict(limit_val_batches=0))  # val_every=0: no validation
        return fit_stage(system, self.folder, steps=rc.steps, device=self.scene.device, trainer_cfg=self.scene.cfg.trainer,
                         checkpoint_every=rc.checkpoint_every, callbacks=[FiniteGradientGuard(), *self.live_callbacks()],
                         val=self.scene.dm.val_dataloader() if rc.val_every > 0 else None,
                         logger_cfg=self.scene.cfg.logger, **val_kw)

    def outputs(self, system: Any, fit: FitResult) -> dict[str, Any]:
        """Held-out metrics (all views), the scene setup and notes, and ``mesh/source``."""

        system.to(self.scene.device).eval()
        with self.clock.part("evaluation"):
            metrics = evaluate_views(system, self.scene.dm.val_dataloader(), chunk=self.scene.cfg.render.chunk)
        metrics.update({"train_seconds_this_process": fit.seconds, "steps": fit.steps,
                        "scene_setup": self.scene.setup.to_dict(), "notes": self.scene.notes,
                        "occupied_fraction": system.occupied_fraction, "evaluated_on": evaluation_views(self.scene.scene)})
        if self.scene.cfg.export.enabled:
            with self.clock.part("meshes"):
                export_source_mesh(self.scene, system.field, self.folder.path / "mesh" / "source")
        if metrics["evaluated_on"] == "held-out views":
            log.info("reconstruction done: held-out PSNR %.2f dB -> %s", metrics["psnr"], self.folder.path)
        else:
            log.warning("reconstruction done: PSNR %.2f dB on %s -> %s", metrics["psnr"], metrics["evaluated_on"],
                        self.folder.path)
        return metrics

    def summary(self, metrics: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in metrics.items() if k.startswith(("psnr", "ssim", "evaluated_on"))}
