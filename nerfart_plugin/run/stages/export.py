"""``stage=export``: meshes of a finished run (at a ``strength``, or a ``mix`` of runs)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from nerfart_plugin.errors import NerfArtError
from nerfart_plugin.export.run_meshes import export_mesh
from nerfart_plugin.run.factories import SceneContext, build_renderer, load_renderer_state
from nerfart_plugin.run.stages.base import StageResult, blended_run


@dataclass
class MeshTarget:
    """Where a blended run's mesh is written from: the export settings (``cfg.export``) and the capture's
    cameras, as :func:`~nerfart_plugin.export.run_meshes.export_mesh` reads them from a scene."""

    cfg: Any
    cameras: Any


class ExportStage:
    """``stage=export``: meshes of ``checkpoint`` (at ``strength``, or the ``mix``) into
    ``<its folder>/mesh/export-<name>-r<resolution><blend tag>.*``."""

    def __init__(self, cfg: Any, checkpoint: Optional[Path], scene: Optional[SceneContext] = None) -> None:
        self.cfg, self.scene = cfg, scene
        self.checkpoint = None if checkpoint is None else Path(checkpoint)

    def run(self) -> StageResult:
        if self.cfg.mix.runs or self.cfg.strength != 1.0:  # a blend (nerfart_plugin.results.blend): read through the run
            run = blended_run(self.cfg, self.checkpoint)
            ckpt, field, target, tag = run.checkpoint, run.renderer.field, MeshTarget(self.cfg, run.cameras), run.tag
        else:
            ckpt, target, tag = self.checkpoint, self.scene, ""
            if not ckpt.exists():
                raise NerfArtError(f"stage=export: no checkpoint at {ckpt}. Run stage=reconstruct first or pass "
                                   "source_checkpoint=/path/to/final.ckpt.")
            renderer = build_renderer(self.scene.cfg, self.scene.setup)
            renderer.load_state_dict(load_renderer_state(ckpt, self.scene))
            field = renderer.to(self.scene.device).eval().field
        stem = ckpt.parent / "mesh" / f"export-{ckpt.stem}-r{self.cfg.export.resolution}{tag}"
        mesh = export_mesh(target, field, stem)
        return StageResult(ckpt, {"mesh": str(stem), "vertices": None if mesh is None else len(mesh.vertices)})


