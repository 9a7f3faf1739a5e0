"""``stage=preview``: a short, small version of the full stylization, with a verdict in words.

A preview runs the full run's own recipe (the same source, style, losses, learning rates, views and per-step
seeds) for ``preview.steps`` steps (40) at a smaller size (``preview.resolution=auto``: a long side of
:data:`PREVIEW_LONG_SIDE` px, or the full run's where that is smaller), with the silhouette term holding the
subject's outline (``preview.lambda_silhouette``). Its held-out views can be shown through the strength dial
(``preview.strength``: θ_src + s·(θ_preview − θ_src)). No video, no meshes. ``preview.png`` shows source | preview
| the full run's view where that run has finished (drawn again when the preview is asked for after the full run),
under the verdict. The recipe is the one measured to resemble the full run most within a minute (BENCHMARKS.md,
"The preview"): the full run's first steps at its own size, pushed on by the dial, resembled it less and lost the
outline on 9 of the study's 15 prompts.

The verdict (:func:`verdict`) reads the guide's directional similarity of the dialed views against thresholds
calibrated on the study's prompts with the guide they were measured with (:data:`CALIBRATION`); for another
guide it says the scores are uncalibrated.
"""

from __future__ import annotations

import copy
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import imageio.v3 as iio
import numpy as np
import torch

from nerfart_plugin.guidance.style import Style
from nerfart_plugin.results.blend import blended_renderer
from nerfart_plugin.run.factories import SceneContext, stylize_settings
from nerfart_plugin.run.fit import FitResult
from nerfart_plugin.run.folders import RunFolder
from nerfart_plugin.run.stages.base import LiveViewerFactory, StageResult
from nerfart_plugin.run.stages.stylize import StylizeStage
from nerfart_plugin.utils.io import atomic_write_json
from nerfart_plugin.utils.images import image_grid, label_image, save_image, side_by_side, to_uint8, with_caption

log = logging.getLogger("nerfart_plugin")

#: the long side (px) of a preview's views with ``preview.resolution=auto`` (at most the full run's)
PREVIEW_LONG_SIDE = 128
#: the least long side (px) of the views in ``preview.png``
PICTURE_LONG_SIDE = 256


@dataclass(frozen=True)
class Calibration:
    """Verdict thresholds on the guide's directional similarity of a preview, for one guide.

    Attributes:
        guide: the ``guidance`` they were measured with; likely / unlikely: at or above ``likely`` "likely to
        work", below ``unlikely`` "unlikely to work", between them "uncertain: run it"; steps / strength /
        silhouette / resolution: the ``preview.steps``, ``preview.strength``, silhouette weight and long side (px)
        they were measured at (the score moves with each); record:
        what the study found (how many prompts each verdict got right), quoted in the verdict.
    """

    guide: str
    likely: float
    unlikely: float
    steps: int
    strength: float
    silhouette: float
    resolution: int
    record: str


#: the verdict's thresholds per guide, from ``python -m benchmarks preview`` (BENCHMARKS.md, "The preview")
CALIBRATION: dict[str, Calibration] = {
    "imagenet": Calibration("imagenet", likely=0.283, unlikely=0.200, steps=40, strength=1.0, silhouette=5.0,
                            resolution=128,
                            record="set on 15 prompts, 12 of which work in a full run: the 8 called likely work, "
                                   "7 uncertain; each judged by thresholds set on the other 14: 8 right, 2 wrong, "
                                   "5 uncertain"),
}


def verdict(direction: Optional[float], guide: str, steps: Optional[int] = None,
            strength: Optional[float] = None, silhouette: Optional[float] = None,
            resolution: Optional[int] = None) -> dict[str, Any]:
    """The preview's verdict on its prompt: ``{"verdict": "likely to work" | "unlikely to work" | "uncertain: run
    it" | "uncalibrated", "why": ..., "score": direction}``; ``steps`` / ``strength`` / ``silhouette`` (the
    preview's silhouette weight) / ``resolution`` (its long side), where given, must be the calibration's."""
    cal = CALIBRATION.get(guide)
    if direction is None:
        return {"verdict": "uncalibrated", "why": "no prompt: a style picture alone has no directional score",
                "score": None}
    if cal is None:
        return {"verdict": "uncalibrated", "why": f"the verdict is calibrated for guidance={', '.join(CALIBRATION)} "
                f"only; compare guidance={guide} previews by their directional similarity", "score": direction}
    measured = {"preview.steps": (steps, cal.steps), "preview.strength": (strength, cal.strength),
                "preview.lambda_silhouette": (silhouette, cal.silhouette), "preview.resolution": (resolution,
                                                                                                  cal.resolution)}
    if any(given is not None and abs(given - at) > 1e-9 for given, at in measured.values()):
        at = " ".join(f"{k}={v[1]:g}" for k, v in measured.items())
        return {"verdict": "uncalibrated", "score": direction,
                "why": f"the verdict is calibrated at {at}; compare these previews by their directional similarity"}
    if direction >= cal.likely:
        word, rule = "likely to work", f">= {cal.likely:.3f}"
    elif direction < cal.unlikely:
        word, rule = "unlikely to work", f"< {cal.unlikely:.3f}"
    else:
        word, rule = "uncertain: run it", f"between {cal.unlikely:.3f} and {cal.likely:.3f}"
    return {"verdict": word, "score": direction,
            "why": f"the guide's directional similarity {direction:.3f} is {rule} ({cal.record})"}


class PreviewStage(StylizeStage):
    """``stage=preview``: the stylization of the same source and style under :func:`preview_scene`'s settings,
    into ``previews/<style>-<backbone>-<key>/``: ``preview.png``, ``heldout/`` (at ``preview.strength``) and
    ``metrics.json`` (the verdict, the guide's and the judge's scores). A finished preview is reused (its verdict
    logged again, its picture completed with the full run's views once that run exists). Previews of settings
    that differ only in the full run's length are one preview."""

    reused_message = "this preview is already complete: %s (not recomputed)"
    stage = "preview"

    def __init__(self, scene: SceneContext, style: Style, source: Path, source_keys: dict[int, str],
                 live: Optional[LiveViewerFactory] = None) -> None:
        self.full_run = StylizeStage(scene, style, source, source_keys).folder  # the run this previews
        super().__init__(preview_scene(scene), style, source, source_keys, live)
        # the dial changes the views shown, not the training: a preview at another strength is another folder
        tag, stamp = ("" if self.strength == 1.0 else f"-s{self.strength:.2f}"), style.stamp
        self.names = [f"{n[:len(n) - len(stamp)]}{tag}{stamp}" for n in self.names]
        self.folder = RunFolder.find(scene.root / "previews", self.names, "preview")

    @property
    def strength(self) -> float:
        """The dial the views are shown at (1 inside a region: the composite is shown as trained)."""
        return 1.0 if self.region is not None else float(self.scene.cfg.preview.strength)

    @property
    def silhouette(self) -> float:
        """The silhouette term's weight in the preview's steps."""
        return float(self.scene.cfg.experiment.lambda_silhouette)

    def outputs(self, system: Any, fit: FitResult) -> dict[str, Any]:
        dialed = None
        if self.strength != 1.0:
            dialed = blended_renderer(system.renderer, system.source, [system.renderer], [self.strength])
        with self.clock.part("evaluation"):
            metrics = self.heldout_metrics(system, renderer=dialed)
        metrics.update({"prompt": self.style.raw_prompt, "prompt_used": self.style.prompt, "style": self.style.name,
                        "steps": fit.steps, "resolution": self.settings.resolution, "strength": self.strength,
                        "lambda_silhouette": self.silhouette,
                        "train_seconds_this_process": fit.seconds, "full_run": str(self.full_run.path),
                        "source_checkpoint": str(Path(self.source).resolve()), "stamp": self.style.stamp or None})
        metrics["verdict"] = self.verdict_of(metrics)
        metrics["picture_has_full_run"] = draw_preview(self.folder.path, metrics, self.full_run)
        log_preview(self.folder.path, metrics)
        return metrics

    def verdict_of(self, metrics: dict[str, Any]) -> dict[str, Any]:
        """The verdict on a preview's scores and settings (``metrics.json``), at this version's thresholds."""
        return verdict(metrics.get("clip_directional_similarity"), self.scene.cfg.guidance.name,
                       metrics.get("steps"), metrics.get("strength"), metrics.get("lambda_silhouette"),
                       metrics.get("resolution"))

    def auto_choices(self, system: Any, fit: FitResult) -> dict[str, Any]:
        return {**super().auto_choices(system, fit), "preview.resolution": self.settings.resolution}

    def reuse(self) -> StageResult:
        result = super().reuse()
        metrics = _read_json(self.folder.path / "metrics.json")
        shown = metrics.get("picture_has_full_run") and metrics.get("full_run") == str(self.full_run.path)
        fresh = self.verdict_of(metrics)  # the thresholds may have been calibrated again since
        if metrics and (fresh != metrics.get("verdict") or (self.full_run.finished and not shown)):
            metrics.update(verdict=fresh, full_run=str(self.full_run.path))  # one preview serves several full runs
            metrics["picture_has_full_run"] = draw_preview(self.folder.path, metrics, self.full_run)
            atomic_write_json(self.folder.path / "metrics.json", metrics)
        log_preview(self.folder.path, metrics)
        return StageResult(result.checkpoint, {**result.summary, **self.summary(metrics)})

    def summary(self, metrics: dict[str, Any]) -> dict[str, Any]:
        return {"preview": str(self.folder.path / "preview.png"), "judge": metrics.get("judge") or {},
                "verdict": (metrics.get("verdict") or {}).get("verdict"),
                **{k: v for k, v in metrics.items() if k.startswith("clip_")}}


def preview_scene(scene: SceneContext) -> SceneContext:
    """``scene`` under the preview's settings: ``preview.steps`` steps at ``preview.resolution`` (auto:
    :data:`PREVIEW_LONG_SIDE`, at most the stylization's own) in place of the stylization's, the silhouette term
    at ``preview.lambda_silhouette`` at least, no video, no saved renders, no meshes."""
    plain = copy.deepcopy(scene.plain)
    pc = scene.cfg.preview
    full_size = int(stylize_settings(scene).resolution)
    size = min(PREVIEW_LONG_SIDE, full_size) if pc.resolution == "auto" else pc.resolution
    update = {"steps": pc.steps, "epochs": None, "video_frames": 0, "render_every": 0, "resolution": size}
    plain["stylize"].update(update)
    experiment = plain["experiment"]
    experiment["lambda_silhouette"] = max(float(experiment["lambda_silhouette"]), float(pc.lambda_silhouette))
    plain["export"]["enabled"] = False
    return scene.with_config(plain)


def draw_preview(folder: Path, metrics: dict[str, Any], full_run: RunFolder) -> bool:
    """``preview.png``: one row per held-out view, source | preview (at its strength) | the full run's view where
    ``full_run`` has finished, under the verdict; True when the full run's views are in it."""
    rows, with_full = [], full_run.finished
    s, steps = metrics.get("strength", 1.0), metrics.get("steps")
    label = f"preview: {steps} steps" + ("" if s == 1.0 else f", at {s:g}x")
    for stylized in sorted((folder / "heldout").glob("stylized_*.png")):
        source = iio.imread(stylized.with_name(stylized.name.replace("stylized_", "source_")))
        h, w = source.shape[:2]
        scale = max(1.0, PICTURE_LONG_SIDE / max(h, w))  # small previews drawn larger, so that they can be read
        hw = (round(h * scale), round(w * scale))
        tiles = [label_image(_resized(source, hw), "source"), label_image(_resized(iio.imread(stylized), hw), label)]
        full = full_run.path / "heldout" / stylized.name
        if with_full and full.is_file():
            tiles.append(label_image(_resized(iio.imread(full), hw), "the full run"))
        row = tiles[0]
        for tile in tiles[1:]:
            row = side_by_side(row, tile, labels=None)
        rows.append(row)
    if not rows:
        return False
    v = metrics.get("verdict") or {}
    caption = f"{metrics.get('style') or metrics.get('prompt')}: {v.get('verdict', 'no verdict')} ({v.get('why', '')})"
    save_image(with_caption(image_grid(rows, ncols=1), caption), folder / "preview.png")
    return with_full


def _resized(img: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    if img.shape[:2] == tuple(hw):
        return to_uint8(img)
    t = torch.from_numpy(to_uint8(img)).permute(2, 0, 1)[None].float()
    out = torch.nn.functional.interpolate(t, size=hw, mode="bilinear", antialias=True)[0].permute(1, 2, 0)
    return out.clamp(0, 255).round().byte().numpy()


def log_preview(folder: Path, metrics: dict[str, Any]) -> None:
    """One line a user reads: the verdict and why, the judge's reading where the prompt names an ImageNet class,
    the distance to a style picture, and where the picture is."""
    v = metrics.get("verdict") or {}
    parts = [f"{v['verdict']} ({v['why']})"] if v else []
    picture = metrics.get("style_image") or {}
    if "nnfm_stylized" in picture:
        parts.append(f"distance to the style picture (the judge's features; lower: closer) {picture['nnfm_source']:.3f} "
                     f"-> {picture['nnfm_stylized']:.3f}, colours {picture['colour_emd_source']:.1f} -> "
                     f"{picture['colour_emd_stylized']:.1f}")
    judge = metrics.get("judge") or {}
    if "stylized" in judge:
        parts.append(f"the judge's P({judge['target_class']}) {judge['source']['mean_target_prob']:.4f} -> "
                     f"{judge['stylized']['mean_target_prob']:.4f}, top-5 on {100 * judge['source']['top5_rate']:.0f}% "
                     f"-> {100 * judge['stylized']['top5_rate']:.0f}% of the held-out views")
    log.info("preview of %r: %s; see %s", metrics.get("style") or metrics.get("prompt"), "; ".join(parts) or "done",
             folder / "preview.png")


def _read_json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
