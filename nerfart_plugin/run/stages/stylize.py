"""``stage=stylize``: the fine-tuning toward a prompt and/or a style picture into
``stylizations/<style>-<backbone>-<key><stamp>/``
(``final.ckpt``, ``heldout/``, ``video<stamp>.mp4``, ``mesh/``, ``metrics.json``)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch
from PIL import Image

from nerfart_plugin.cameras.capture import scale_intrinsics
from nerfart_plugin.cameras.orbits import orbit_path
from nerfart_plugin.cameras.path import RenderPath
from nerfart_plugin.export.compare import compare_meshes, displacement_mesh, vertex_distances
from nerfart_plugin.export.run_meshes import export_mesh, export_source_mesh, write_in_frame
from nerfart_plugin.export.video import write_video
from nerfart_plugin.guidance.style import Style, style_choices
from nerfart_plugin.objectives.evaluation import (clip_scores, edge_similarity, evaluation_views, judge_prompt,
    lost_subject, off_surface_share, region_metrics, silhouette_iou, view_consistency)
from nerfart_plugin.objectives.style_distance import style_image_metrics
from nerfart_plugin.rendering.frames import render_cameras
from nerfart_plugin.run.factories import SceneContext, build_stylization_system, load_renderer_state, stylize_settings
from nerfart_plugin.run.fit import FitResult, fit_stage
from nerfart_plugin.run.folders import RunFolder
from nerfart_plugin.regions.region import region_from_config
from nerfart_plugin.results.run import REGION_FILE
from nerfart_plugin.run.keys import checkpoint_keys, stylization_keys
from nerfart_plugin.run.stages.base import LiveViewerFactory, TrainingStage
from nerfart_plugin.run.stages.reconstruct import ReconstructStage
from nerfart_plugin.utils.device import to_device
from nerfart_plugin.utils.images import to_uint8
from nerfart_plugin.utils.io import atomic_path, slug

log = logging.getLogger("nerfart_plugin")


#: rays that stay this many occupancy cells clear of a region's geometry are "outside" it: they cross only cells
#: the stylization held as the source's (:attr:`~nerfart_plugin.fields.occupancy.OccupancyGrid.keep`)
OUTSIDE_CELLS = 2.5


class StylizeStage(TrainingStage):
    """Stage 2: stylize the reconstruction ``source`` toward the prompt of ``style``
    (:class:`~nerfart_plugin.systems.StylizationSystem`).

    Args:
        source: the reconstruction's ``final.ckpt``; source_keys: what identifies it in the key, per settings
            format (the reconstruction's keys, or those of an explicit ``source_checkpoint``: :mod:`~nerfart_plugin.run.keys`).
    """

    reused_message = "this stylization is already complete: %s (not recomputed, not overwritten)"
    kind, stage = "stylization", "stylize"

    def __init__(self, scene: SceneContext, style: Style, source: Path, source_keys: dict[int, str],
                 live: Optional[LiveViewerFactory] = None) -> None:
        super().__init__(scene, live)
        c = scene.cfg
        self.style, self.source = style, source
        self.settings = stylize_settings(scene, style)
        self.region = region_from_config(c.region)
        self.keys = stylization_keys(scene, style, source_keys, stylize_settings(scene))
        self.names = [f"{slug(style.name)}-{c.backbone.name}-{key}{style.stamp}" for key in self.keys.values()]
        self.folder = RunFolder.find(scene.root / "stylizations", self.names, "stylization")
        self.source_state: Optional[dict] = None

    @property
    def source_run(self) -> Optional[Path]:
        return Path(self.source).parent

    def check_inputs(self) -> None:
        """The source renderer's tensors, read safely and checked to fit this run's model."""
        self.source_state = load_renderer_state(self.source, self.scene)

    def build_system(self) -> Any:
        if self.region is not None:  # the folder says where it stylizes (open_run renders the composite from it)
            self.region.save(self.folder.path / REGION_FILE)
        return build_stylization_system(self.scene, self.source_state, self.style, out_dir=self.folder.path)

    def fit(self, system: Any) -> FitResult:
        return fit_stage(system, self.folder, steps=self.settings.steps, device=self.scene.device,
                         trainer_cfg=self.scene.cfg.trainer, checkpoint_every=self.settings.checkpoint_every,
                         callbacks=self.live_callbacks(), logger_cfg=self.scene.cfg.logger, limit_val_batches=0)

    def outputs(self, system: Any, fit: FitResult) -> dict[str, Any]:
        """Metrics on held-out views, the side-by-side video, meshes and their comparison."""
        c, st = self.scene.cfg, self.style
        with self.clock.part("evaluation"):
            metrics = self.heldout_metrics(system)
        with self.clock.part("video"):
            metrics.update(self.video(system))
        if c.export.enabled:
            with self.clock.part("meshes"):
                metrics.update(self.compare_meshes(system))
        metrics.update({"prompt": st.raw_prompt, "prompt_used": st.prompt, "source_prompt": st.source_prompt,
                        "style": st.name,
                        "guidance": c.guidance.name, "guidance_is_real": st.real, "stamp": st.stamp or None,
                        "experiment": c.experiment.model_dump(mode="json"), "steps": fit.steps,
                        "train_seconds_this_process": fit.seconds, "last_step_timings_s": system.timings,
                        "source_checkpoint": str(Path(self.source).resolve()),
                        **system.negatives_report()})

        warnings = [w for w in (st.warning, lost_subject(metrics.get("silhouette_iou"))) if w]
        if warnings:
            metrics["WARNING"] = "; ".join(warnings)
        log.info("stylization done -> %s", self.folder.path)
        return metrics

    def summary(self, metrics: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in metrics.items() if k.startswith(("clip_", "view_", "mesh_"))}

    def auto_choices(self, system: Any, fit: FitResult) -> dict[str, Any]:
        return {**super().auto_choices(system, fit), **style_choices(self.style, self.settings, self.scene.cfg)}

    @torch.no_grad()
    def heldout_metrics(self, system: Any, renderer: Optional[Any] = None) -> dict[str, Any]:
        """CLIP scores, colour means, edge similarity, silhouette IoU, the judge and the off-surface weight
        on the held-out views (``heldout/`` images saved); ``renderer``: what renders the stylization (default
        the system's own view; a preview passes its field at its strength)."""

        system.to(self.scene.device).eval()
        scene = self.scene.scene
        ids = scene.val_ids or scene.train_ids[:4]
        views = self.scene.views(ids, self.settings.resolution)
        stylized = renderer if renderer is not None else system.view
        sty_out = [system.render_view(v, chunk=self.settings.chunk, with_normals=False, renderer=stylized)
                   for v in views]
        src_out = [system.render_batch(v, source=True) for v in views]
        sty = torch.stack([o["rgb"].permute(2, 0, 1) for o in sty_out]).clamp(0, 1)
        src = torch.stack([o["rgb"].permute(2, 0, 1) for o in src_out]).clamp(0, 1)
        metrics: dict[str, Any] = {}
        if self.style.text:
            metrics.update(clip_scores(system.guidance, sty, src, system.tgt_txt, system.src_txt))
        if self.style.image is not None:
            metrics["style_image"] = {"file": str(self.style.image.file), "content": self.style.image.content_hash,
                                      **style_image_metrics(self.style.image.image.to(sty.device), src, sty,
                                                            _opacities(src_out), _opacities(sty_out))}
        metrics["mean_rgb"] = [float(x) for x in sty.mean((0, 2, 3))]
        metrics["mean_rgb_source"] = [float(x) for x in src.mean((0, 2, 3))]
        metrics["edge_similarity"] = edge_similarity(sty, src)
        metrics["silhouette_iou"] = silhouette_iou(_opacities(src_out), _opacities(sty_out))
        self.save_heldout(ids, src, sty)
        if self.region is not None:  # outside: the rays clear of the region and of the occupancy cells it reaches
            grid = system.view.occupancy
            reach = OUTSIDE_CELLS * grid.cell_size if grid is not None else 0.0
            metrics["region"] = region_metrics(self.style.raw_prompt or "", system.view.field.regions[0].grown(reach), views,
                                               src, sty, ids)
        metrics["judge"] = (judge_prompt(self.style.raw_prompt, src, sty, ids) if self.style.text
                            else {"skipped": "no prompt: a style picture alone (see style_image)"})
        metrics["evaluated_on"] = evaluation_views(scene)

        dev = self.scene.device
        metrics["off_surface_weight"] = float(np.mean([off_surface_share(stylized, to_device(v, dev))
                                                       for v in views]))
        metrics["off_surface_weight_source"] = float(np.mean([off_surface_share(system.source, to_device(v, dev))
                                                              for v in views]))
        return metrics

    def save_heldout(self, ids: list[int], src: torch.Tensor, sty: torch.Tensor) -> None:
        """``heldout/source_<view>.png`` and ``heldout/stylized_<view>.png`` at the stylization resolution."""

        for i, a, b in zip(ids, src, sty):
            for name, img in (("source", a), ("stylized", b)):
                with atomic_path(self.folder.path / "heldout" / f"{name}_{int(i):04d}.png") as tmp:
                    Image.fromarray(to_uint8(img.permute(1, 2, 0))).save(tmp, format="PNG")

    @torch.no_grad()
    def video(self, system: Any) -> dict[str, Any]:
        """The source | stylized orbit video (``stylize.video_frames`` frames at the stylization size) and the
        view-consistency error along it; nothing with ``stylize.video_frames=0``."""

        sc, stamp, scene = self.settings, self.style.stamp, self.scene.scene
        metrics: dict[str, Any] = {"view_consistency_error": None}
        if sc.video_frames <= 0:
            return metrics
        ref = self.scene.views(scene.train_ids[:1] or [0], sc.resolution)[0]
        c2ws = orbit_path(scene, sc.video_frames)
        K = scale_intrinsics(scene.K[0], ref["W"] / scene.width, ref["H"] / scene.height)
        path = RenderPath("orbit", c2ws, K.expand(len(c2ws), 3, 3), int(ref["H"]), int(ref["W"]))
        label = "stylized" + (f" ({stamp.strip('_')})" if stamp else "")
        rendered: dict[str, list] = {}
        frames = render_cameras(system.view, path, ndc=self.scene.ndc, near=float(scene.near.min()),
                                far=float(scene.far.max()), chunk=sc.chunk, device=self.scene.device,
                                channels=("side",), source=system.source, labels=("source", label), progress=False,
                                outputs=rendered)["side"]
        write_video(frames, self.folder.path / f"video{stamp}.mp4", fps=sc.video_fps)
        if not self.scene.ndc:  # NDC: depth is NDC t, warping not implemented: view_consistency_error stays None
            Kd = K.to(self.scene.device)
            metrics["view_consistency_error"] = view_consistency(rendered["rendered"], Kd, c2ws)
            metrics["view_consistency_error_source"] = view_consistency(rendered["source"], Kd, c2ws)
        return metrics

    def compare_meshes(self, system: Any) -> dict[str, Any]:
        """``mesh/source``, ``mesh/stylized<stamp>``, ``mesh/displacement<stamp>.ply`` and the geometry change."""

        stamp, mesh_dir = self.style.stamp, self.folder.path / "mesh"
        src = export_source_mesh(self.scene, system.source.field, mesh_dir / "source",
                                 shared=Path(self.source).parent / "mesh" / "source")
        sty = export_mesh(self.scene, system.view.field, mesh_dir / f"stylized{stamp}")
        if src is None or sty is None:
            return {}
        sdf = system.source.field.signed_distance()
        m = compare_meshes(sty, src, n_samples=20_000, source_sdf=sdf)
        write_in_frame(self.scene, displacement_mesh(sty, vertex_distances(sty, src, source_sdf=sdf)),
                       mesh_dir / f"displacement{stamp}.ply")
        return {f"mesh_{k}": v for k, v in m.items()}


def stylization_source(scene: SceneContext, recon: Optional[ReconstructStage]) -> tuple[Path, dict[int, str]]:
    """The checkpoint a stylization starts from and what identifies it in the stylization key (per settings
    format): the cached reconstruction of these settings (its keys cover the scene, data and render settings), or
    an explicit ``source_checkpoint`` (:func:`~nerfart_plugin.run.keys.checkpoint_keys`)."""
    src = scene.cfg.source_checkpoint
    if src:
        return Path(src), checkpoint_keys(scene, Path(src))
    assert recon is not None
    return recon.folder.final, recon.keys


def _opacities(outs: list[dict[str, torch.Tensor]]) -> torch.Tensor:
    """[B,H,W] the opacity images of renders (dicts with ``opacity`` [H,W,1])."""
    return torch.stack([o["opacity"][..., 0] for o in outs])
