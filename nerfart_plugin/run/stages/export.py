"""``stage=export``: meshes of a finished run (at a ``strength``, or a ``mix`` of runs)."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from nerfart_plugin.config.validate import result_settings
from nerfart_plugin.errors import NerfArtError
from nerfart_plugin.export.run_meshes import export_mesh, recall_mesh, remember_mesh, tensors_hash
from nerfart_plugin.export.splats import SplatFit, export_splats
from nerfart_plugin.results.run import Run
from nerfart_plugin.run.factories import SceneContext, checkpoint_run
from nerfart_plugin.run.stages.base import StageResult, blended_run
from nerfart_plugin.utils.io import atomic_write_json, config_hash
from nerfart_plugin.utils.lock import run_lock

log = logging.getLogger("nerfart_plugin")


@dataclass
class MeshTarget:
    """Where a blended run's mesh is written from: the export settings (``cfg.export``) and the capture's
    cameras, as :func:`~nerfart_plugin.export.run_meshes.export_mesh` reads them from a scene."""

    cfg: Any
    cameras: Any


class ExportStage:
    """``stage=export``: meshes of the run of ``checkpoint`` (at ``strength``), or of the ``mix``, into
    ``<its folder>/mesh/export-<name>-r<resolution><blend tag>.*`` (the export settings of ``cfg``). With the
    run's ``scene`` and no blend, the checkpoint is read as a run of the scene's settings, checked to fit them."""

    def __init__(self, cfg: Any, checkpoint: Optional[Path], scene: Optional[SceneContext] = None) -> None:
        self.cfg, self.scene = cfg, scene
        self.checkpoint = None if checkpoint is None else Path(checkpoint)

    def run(self) -> StageResult:
        if not self.cfg.mix.runs and not self.checkpoint.exists():
            raise NerfArtError(f"stage=export: no checkpoint at {self.checkpoint}. Run stage=reconstruct first or pass "
                               "source_checkpoint=/path/to/final.ckpt.")
        blend = self.cfg.mix.runs or self.cfg.strength != 1.0 or self.scene is None
        run = blended_run(self.cfg, self.checkpoint) if blend else checkpoint_run(self.checkpoint, self.scene)
        ckpt = run.checkpoint
        stem = ckpt.parent / "mesh" / f"export-{ckpt.stem}-r{self.cfg.export.resolution}{run.tag}"
        with run_lock(stem, self.cfg.lock_timeout):  # two exports of one output: the second waits, then reuses
            mesh_key, splat_key = export_keys(run, self.cfg)
            summary = {"mesh": str(stem), "vertices": self.mesh(run, stem, mesh_key)}
            if self.cfg.export.splats:
                summary["splats"] = self.splats(run, ckpt.parent / "splats" /
                                                f"{stem.name.replace('export-', 'splats-')}.ply", splat_key)
        return StageResult(ckpt, summary)

    def mesh(self, run: Run, stem: Path, key: str) -> Optional[int]:
        """The run's mesh files at ``stem`` (their vertex count; None: no surface): the ones already there when
        they were written under ``key`` (the same field, blend and export settings), else extracted again."""
        recalled = recall_mesh(stem, key)
        if recalled is not None:
            log.info("export: %s is up to date (the same run, blend and export settings); reused", stem)
            return len(recalled[0].vertices)
        mesh = export_mesh(MeshTarget(self.cfg, run.cameras), run.renderer.field, stem)
        if mesh is None:
            return None
        remember_mesh(stem, mesh, key, self.cfg.export.formats)
        return len(mesh.vertices)

    def splats(self, run: Run, path: Path, key: str) -> dict[str, Any]:
        """The run's field as splats at ``path`` (:func:`~nerfart_plugin.export.splats.export_splats`), recorded in
        the run's ``metrics.json`` under ``splats`` (by file name) with ``key``; a file already there under the
        same key is reused."""
        metrics_file = Path(run.folder) / "metrics.json"
        metrics = json.loads(metrics_file.read_text()) if metrics_file.is_file() else {}
        stored = metrics.get("splats", {}).get(path.name)
        if isinstance(stored, dict) and stored.get("key") == key and path.is_file():
            log.info("export: %s is up to date (the same run, blend and splat settings); reused", path)
            return stored
        ec = self.cfg.export
        fit = SplatFit(count=ec.splat_count, steps=ec.splat_steps, resolution=ec.splat_resolution, seed=self.cfg.seed)
        report = {**export_splats(run, path, fit, frame=ec.frame), "key": key}
        metrics = json.loads(metrics_file.read_text()) if metrics_file.is_file() else {}
        metrics.setdefault("splats", {})[path.name] = report
        atomic_write_json(metrics_file, metrics)
        return report


def export_keys(run: Run, cfg: Any) -> tuple[str, str]:
    """What a run's exported files depend on, (meshes, splats): its field's tensors (a blend's or region's
    composite included), the blend, the capture's frame (normalization) and the export settings that change
    results: the mesh's, and for the splats the splat fit's too (and the seed it draws from)."""
    settings = result_settings(cfg.export)
    common = {"field": tensors_hash(run.renderer.field), "blend": run.tag,
              "frame": [list(map(float, row)) for row in run.cameras.normalization]}
    mesh = {k: v for k, v in settings.items() if not k.startswith("splat")}
    return (config_hash({**common, "export": mesh, "seed": None}, n=64),
            config_hash({**common, "export": settings, "seed": cfg.seed}, n=64))
