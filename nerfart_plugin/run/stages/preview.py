"""``stage=preview``: a short, low-resolution stylization that says in about a minute how a prompt will go.

Same source, prompt, guide and losses as the full stylization (:class:`~nerfart_plugin.run.stages.stylize.StylizeStage`),
``preview.steps`` steps at ``preview.resolution`` px, no video, no meshes; the log line gives the guide's
directional similarity (any prompt) and the judge's verdict (prompts naming an ImageNet class).
"""

from __future__ import annotations

import copy
import json
import logging
from pathlib import Path
from typing import Any, Optional

from nerfart_plugin.guidance.style import Style
from nerfart_plugin.run.factories import SceneContext
from nerfart_plugin.run.fit import FitResult
from nerfart_plugin.run.folders import RunFolder
from nerfart_plugin.run.stages.base import LiveViewerFactory, StageResult
from nerfart_plugin.run.stages.stylize import StylizeStage
from nerfart_plugin.utils.images import image_grid, save_image, side_by_side

log = logging.getLogger("nerfart_plugin")


class PreviewStage(StylizeStage):
    """``stage=preview``: the stylization of the same source, prompt and losses, shortened to ``preview.steps``
    steps at ``preview.resolution`` px, without video or meshes, into ``previews/<prompt>-<backbone>-<key>/``:
    ``preview.png`` (source | preview on the held-out views), ``heldout/`` and ``metrics.json`` with the
    guide's and the judge's scores. A finished preview is reused (its scores logged again)."""

    reused_message = "this preview is already complete: %s (not recomputed)"
    stage = "preview"

    def __init__(self, scene: SceneContext, style: Style, source: Path, source_keys: dict[int, str],
                 live: Optional[LiveViewerFactory] = None) -> None:
        super().__init__(preview_scene(scene), style, source, source_keys, live)
        self.folder = RunFolder.find(scene.root / "previews", self.names, "preview")

    def outputs(self, system: Any, fit: FitResult) -> dict[str, Any]:
        with self.clock.part("evaluation"):
            metrics = self.heldout_metrics(system)
        _, src, sty = self.heldout_views
        rows = [side_by_side(a.permute(1, 2, 0), b.permute(1, 2, 0), labels=("source", f"preview, {fit.steps} steps"))
                for a, b in zip(src, sty)]
        save_image(image_grid(rows, ncols=1), self.folder.path / "preview.png")
        metrics.update({"prompt": self.style.raw_prompt, "prompt_used": self.style.prompt, "style": self.style.name,
                        "steps": fit.steps,
                        "resolution": self.settings.resolution, "train_seconds_this_process": fit.seconds,
                        "source_checkpoint": str(Path(self.source).resolve()), "stamp": self.style.stamp or None})
        log_preview(self.folder.path, metrics)
        return metrics

    def reuse(self) -> StageResult:
        result = super().reuse()
        metrics = _read_json(self.folder.path / "metrics.json")
        log_preview(self.folder.path, metrics)
        return StageResult(result.checkpoint, {**result.summary, **self.summary(metrics)})

    def summary(self, metrics: dict[str, Any]) -> dict[str, Any]:
        judge = metrics.get("judge") or {}
        return {"preview": str(self.folder.path / "preview.png"), "judge": judge,
                **{k: v for k, v in metrics.items() if k.startswith("clip_")}}


def preview_scene(scene: SceneContext) -> SceneContext:
    """``scene`` under the preview's settings: ``preview.steps`` / ``preview.resolution`` in place of the
    stylization's, no video, no saved renders, no meshes."""

    plain = copy.deepcopy(scene.plain)
    pc = scene.cfg.preview
    plain["stylize"].update(steps=pc.steps, epochs=None, resolution=pc.resolution, video_frames=0, render_every=0)
    plain["export"]["enabled"] = False
    return scene.with_config(plain)


def log_preview(folder: Path, metrics: dict[str, Any]) -> None:
    """One line a user reads: how far the guide moved the views toward the prompt (any prompt; compare prompts by
    it), the judge's verdict where the prompt names an ImageNet class, and where the picture is."""
    direction = metrics.get("clip_directional_similarity")
    guide = "" if direction is None else f"the guide's directional similarity {direction:.3f} (higher: a stronger " \
                                         "full run, to compare prompts by); "
    picture = metrics.get("style_image") or {}
    if "nnfm_stylized" in picture:
        guide += (f"distance to the style picture (the judge's features; lower: closer) {picture['nnfm_source']:.3f} "
                  f"-> {picture['nnfm_stylized']:.3f}, colours {picture['colour_emd_source']:.1f} -> "
                  f"{picture['colour_emd_stylized']:.1f}; ")
    judge = metrics.get("judge") or {}
    if "stylized" in judge:
        log.info("preview of %r: %sthe judge's P(%s) %.4f -> %.4f, top-5 on %.0f%% -> %.0f%% of the held-out "
                 "views; see %s", metrics.get("style") or metrics.get("prompt"), guide, judge["target_class"],
                 judge["source"]["mean_target_prob"], judge["stylized"]["mean_target_prob"],
                 100 * judge["source"]["top5_rate"], 100 * judge["stylized"]["top5_rate"], folder / "preview.png")
    else:
        log.info("preview of %r: %sjudge: %s; see %s", metrics.get("style") or metrics.get("prompt"), guide, judge.get("skipped", "none"),
                 folder / "preview.png")


def _read_json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
