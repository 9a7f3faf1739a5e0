"""``stage=reconstruct``: fit the field to the photos into ``reconstructions/<data>-<backbone>-<encoding>-<key>/``
(``final.ckpt``, ``metrics.json`` with held-out PSNR / SSIM and the scene setup, ``val/`` images,
``mesh/source.*``)."""

from __future__ import annotations

import logging
from typing import Any


from nerfart_plugin.export.run_meshes import export_source_mesh
from nerfart_plugin.run.factories import (SceneContext, build_reconstruction_system)
from nerfart_plugin.run.fit import FitResult, fit_stage
from nerfart_plugin.run.folders import RunFolder
from nerfart_plugin.utils.io import config_hash
from nerfart_plugin.config.schema import component_result_settings, result_settings

from nerfart_plugin.run.stages.base import TrainingStage

log = logging.getLogger("nerfart_plugin")


def reconstruction_key(scene: SceneContext) -> str:
    """Hash of the scene's content and every setting that changes the reconstruction (the schema's
    ``changes_results`` fields of render / reconstruct / trainer, the component sections, the seed)."""
    c = scene.cfg
    return config_hash({**scene_settings(scene), "backbone": c.backbone, "encoding": c.encoding,
                        "reconstruct": result_settings(c.reconstruct), "trainer": result_settings(c.trainer),
                        "seed": c.seed})


def scene_settings(scene: SceneContext) -> dict[str, Any]:
    """What identifies the photos and how they are rendered, in every key that depends on them: the scene's
    content and the ``changes_results`` settings of data and render."""
    c = scene.cfg
    return {"scene": scene.scene.content_hash, "data": component_result_settings("data", c.data),
            "render": result_settings(c.render)}


class ReconstructStage(TrainingStage):
    """Stage 1: fit the field to the photos (:class:`~nerfart_plugin.systems.ReconstructionSystem`)."""

    reused_message = "reusing the cached reconstruction %s (same data, backbone and settings)"

    def __init__(self, scene: SceneContext) -> None:
        super().__init__(scene)
        c = scene.cfg
        self.key = reconstruction_key(scene)
        name = f"{c.data['kind']}-{c.backbone['name']}-{c.encoding['name']}-{self.key}"
        self.folder = RunFolder(scene.root / "reconstructions" / name, "reconstruction")

    def build_system(self) -> Any:
        return build_reconstruction_system(self.scene, out_dir=self.folder.path)

    def fit(self, system: Any) -> FitResult:
        from nerfart_plugin.systems.callbacks import FiniteGradientGuard

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
        from nerfart_plugin.objectives.evaluation import evaluate_views, evaluation_views

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
