"""The stages that read a finished run instead of training one: ``stage=render`` (videos along a camera path)
and ``stage=export`` (meshes), each of a run at a ``strength`` or of a ``mix`` of runs
(:mod:`nerfart_plugin.blend`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from nerfart_plugin.auto import recorded
from nerfart_plugin.errors import NerfArtError
from nerfart_plugin.export.run_meshes import export_mesh
from nerfart_plugin.factories import SceneContext, build_renderer, load_renderer_state
from nerfart_plugin.stages import StageResult


def blended_run(cfg: Any, folder: Optional[Path]) -> Any:
    """The :class:`~nerfart_plugin.api.Run` that ``stage=render`` / ``stage=export`` work on: ``mix.runs`` at
    ``mix.weights`` when given, else ``folder`` (a run folder or a checkpoint in one) at ``strength``."""
    from nerfart_plugin.api import mix, open_run

    if cfg.mix.runs:
        return mix([open_run(Path(r).expanduser(), device=cfg.device) for r in cfg.mix.runs], cfg.mix.weights)
    run = open_run(folder, device=cfg.device)
    return run if cfg.strength == 1.0 else run.with_strength(cfg.strength)


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
        if self.cfg.mix.runs or self.cfg.strength != 1.0:  # a blend (nerfart_plugin.blend): read through the run
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


class RenderStage:
    """``stage=render``: videos of a finished run along ``render.path`` into ``<run>/render/<path>-<F>f-<W>x<H>/``
    (:meth:`nerfart_plugin.api.Run.write_render`); nothing is trained."""

    def __init__(self, cfg: Any, run_dir: Optional[Path]) -> None:
        self.cfg, self.run_dir = cfg, None if run_dir is None else Path(run_dir)

    def run(self) -> StageResult:
        rc = self.cfg.render
        run = blended_run(self.cfg, self.run_dir)
        resolution = None if rc.resolution == "auto" else int(rc.resolution)
        path = run.camera_path(rc.path, rc.frames, resolution, rc.path_frame)
        summary = run.write_render(run.render_folder(path), path, channels=rc.channels, fps=rc.fps, png=rc.png)
        summary["auto"] = recorded(self.cfg, {"render.resolution": max(path.width, path.height)})
        return StageResult(run.checkpoint, summary)
