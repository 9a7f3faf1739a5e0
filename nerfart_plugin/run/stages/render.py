"""``stage=render``: videos of a finished run along a camera path (at a ``strength``, or a ``mix`` of runs)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import torch

from nerfart_plugin.config.auto import recorded
from nerfart_plugin.fields.compiled import MIN_COMPILED_FRAMES, apply_compile
from nerfart_plugin.run.stages.base import StageResult, blended_run


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
        compiled = apply_compile(run.renderer, self.cfg.compile, torch.device(run.device), len(path),
                                 MIN_COMPILED_FRAMES, "frames")
        summary = run.write_render(run.render_folder(path), path, channels=rc.channels, fps=rc.fps, png=rc.png)
        summary["auto"] = recorded(self.cfg, {"render.resolution": max(path.width, path.height),
                                              "compile": compiled})
        return StageResult(run.checkpoint, summary)
