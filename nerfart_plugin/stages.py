"""One object per stage: its cache key, its run folder, its system and its outputs.

* :class:`ReconstructStage`: ``reconstructions/<data>-<backbone>-<encoding>-<key>/``;
  ``final.ckpt``, ``last.ckpt``, ``metrics.json`` (held-out PSNR / SSIM, the scene setup
  and why), ``val/`` images, ``mesh/source.ply``, CSV logs.
* :class:`StylizeStage`: ``stylizations/<prompt>-<backbone>-<key><stamp>/``; ``final.ckpt``,
  ``renders/``, ``heldout/``, ``video<stamp>.mp4``, ``mesh/``, ``metrics.json``.
* :class:`~nerfart_plugin.preview.PreviewStage` (``stage=preview``) and the stages that read a finished run
  (:mod:`nerfart_plugin.output_stages`: render, export) live beside this module.

Both training stages run the same skeleton (:meth:`TrainingStage.run`): reuse a finished
run, else lock the folder, prepare it, build the system, :func:`~nerfart_plugin.fit.fit_stage`
(resume, atomic checkpoints, Ctrl-C, OOM), write the outputs and ``metrics.json`` on rank 0,
then ``final.ckpt``.
"""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Optional

import numpy as np
import torch

from nerfart_plugin.auto import component_choices, recorded
from nerfart_plugin.export.run_meshes import export_mesh, export_source_mesh, write_in_frame
from nerfart_plugin.factories import (SceneContext, Style, build_reconstruction_system, build_stylization_system,
                                      load_renderer_state, style_choices, stylize_settings)
from nerfart_plugin.fit import FitResult, fit_stage, publish_final, stage_final
from nerfart_plugin.runs import RunFolder, config_hash, slug
from nerfart_plugin.schema import component_result_settings, result_settings
from nerfart_plugin.utils.io import atomic_path, atomic_write_json, hash_files

log = logging.getLogger("nerfart_plugin")


@dataclass
class StageResult:
    """What a stage leaves: its checkpoint and the summary that goes into the run's ``result.json``."""

    checkpoint: Path
    summary: dict[str, Any] = field(default_factory=dict)


class StageClock:
    """Wall seconds of the parts of a stage (fit, evaluation, video, meshes), kept in ``metrics.json`` as
    ``stage_seconds`` so that a user (and the main-job benchmark) sees where the time went."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def part(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = round(self.seconds.get(name, 0.0) + time.perf_counter() - t0, 3)


class TrainingStage:
    """The skeleton both training stages share; subclasses say what is trained and what is written."""

    folder: RunFolder

    def __init__(self, scene: SceneContext) -> None:
        self.scene = scene
        self.clock = StageClock()

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
        publish_final(staged, self.folder)
        return StageResult(self.folder.final, {"dir": str(self.folder.path), **self.summary(metrics)})

    # ---- what a stage says
    reused_message = "reusing %s"

    def check_inputs(self) -> None:
        """Read and check what the stage starts from (nothing by default)."""

    def live_callbacks(self) -> list[Any]:
        """The live viewer on the field being trained, when ``viewer.live`` (:mod:`nerfart_plugin.viewer.live`)."""
        vc = self.scene.cfg.viewer
        if not vc.live:
            return []
        from nerfart_plugin.data.camera_path import CaptureCameras
        from nerfart_plugin.viewer.live import LiveViewer

        from nerfart_plugin.viewer.panels import thumbnails

        scene = self.scene.scene
        cams = CaptureCameras.from_scene(scene, self.scene.ndc)
        return [LiveViewer(cams, host=vc.host, port=vc.port, render_share=vc.render_share,
                           chunk=self.scene.cfg.render.chunk, folder=self.folder.path, title=self.folder.what,
                           photos=thumbnails(scene.images.numpy()))]

    def auto_choices(self, system: Any, fit: FitResult) -> dict[str, Any]:
        """What the run's ``auto`` settings became (:mod:`nerfart_plugin.auto`): the scene's, the data's, the
        compute's and the components' (the field, and for a stylization its guide and perceptual network)."""
        scene = self.scene.scene
        return {**self.scene.setup.auto_choices(), "data.resolution": max(scene.height, scene.width),
                "device": self.scene.device, "trainer.strategy": type(fit.trainer.strategy).__name__,
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


# ---------------------------------------------------------------------- stage 1
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
        from nerfart_plugin.evaluation import evaluate_views, evaluation_views

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


# ---------------------------------------------------------------------- stage 2
class StylizeStage(TrainingStage):
    """Stage 2: stylize the reconstruction ``source`` toward the prompt of ``style``
    (:class:`~nerfart_plugin.systems.StylizationSystem`).

    Args:
        source: the reconstruction's ``final.ckpt``; source_key: what identifies it in the key (the
            reconstruction key, or the resolved path of an explicit ``source_checkpoint``).
    """

    reused_message = "this stylization is already complete: %s (not recomputed, not overwritten)"

    def __init__(self, scene: SceneContext, style: Style, source: Path, source_key: str) -> None:
        super().__init__(scene)
        c = scene.cfg
        self.style, self.source = style, source
        self.settings = stylize_settings(scene, style)
        self.key = config_hash({"recon": source_key, "prompt": style.prompt, "source_prompt": style.source_prompt,
                                "guidance": c.guidance, "experiment": result_settings(c.experiment),
                                # as keyed before the threshold was resolved here: existing runs keep their keys
                                "stylize": result_settings(stylize_settings(scene)),
                                "trainer": result_settings(c.trainer),
                                "seed": c.seed})
        name = f"{slug(style.raw_prompt)}-{c.backbone['name']}-{self.key}{style.stamp}"
        self.folder = RunFolder(scene.root / "stylizations" / name, "stylization")
        self.source_state: Optional[dict] = None
        self.heldout_views: Optional[tuple[list[int], torch.Tensor, torch.Tensor]] = None  # (ids, source, stylized)

    def check_inputs(self) -> None:
        """The source renderer's tensors, read safely and checked to fit this run's model."""
        self.source_state = load_renderer_state(self.source, self.scene)

    def build_system(self) -> Any:
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
                        "guidance": c.guidance["name"], "guidance_is_real": st.real, "stamp": st.stamp or None,
                        "experiment": c.experiment.model_dump(mode="json"), "steps": fit.steps,
                        "train_seconds_this_process": fit.seconds, "last_step_timings_s": system.timings,
                        "source_checkpoint": str(Path(self.source).resolve()),
                        **system.negatives_report()})
        from nerfart_plugin.evaluation import lost_subject

        warnings = [w for w in (st.warning, lost_subject(metrics.get("silhouette_iou"))) if w]
        if warnings:
            metrics["WARNING"] = "; ".join(warnings)
        log.info("stylization done -> %s", self.folder.path)
        return metrics

    def summary(self, metrics: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in metrics.items() if k.startswith(("clip_", "view_", "mesh_"))}

    def auto_choices(self, system: Any, fit: FitResult) -> dict[str, Any]:
        return {**super().auto_choices(system, fit), **style_choices(self.style, self.settings)}

    @torch.no_grad()
    def heldout_metrics(self, system: Any) -> dict[str, Any]:
        """CLIP scores, colour means, edge similarity, silhouette IoU, the judge and the off-surface weight
        on the held-out views (``heldout/`` images saved)."""
        from nerfart_plugin.evaluation import (clip_scores, edge_similarity, evaluation_views, judge_prompt,
                                               off_surface_share, silhouette_iou)

        system.to(self.scene.device).eval()
        scene = self.scene.scene
        ids = scene.val_ids or scene.train_ids[:4]
        views = self.scene.views(ids, self.settings.resolution)
        sty_out = [system.render_batch(v) for v in views]
        src_out = [system.render_batch(v, source=True) for v in views]
        sty = torch.stack([o["rgb"].permute(2, 0, 1) for o in sty_out]).clamp(0, 1)
        src = torch.stack([o["rgb"].permute(2, 0, 1) for o in src_out]).clamp(0, 1)
        metrics: dict[str, Any] = clip_scores(system.guidance, sty, src, system.tgt_txt, system.src_txt)
        metrics["mean_rgb"] = [float(x) for x in sty.mean((0, 2, 3))]
        metrics["mean_rgb_source"] = [float(x) for x in src.mean((0, 2, 3))]
        metrics["edge_similarity"] = edge_similarity(sty, src)
        metrics["silhouette_iou"] = silhouette_iou(torch.stack([o["opacity"][..., 0] for o in src_out]),
                                                   torch.stack([o["opacity"][..., 0] for o in sty_out]))
        self.save_heldout(ids, src, sty)
        self.heldout_views = (ids, src, sty)  # what a preview shows, without reading the PNGs back
        metrics["judge"] = judge_prompt(self.style.raw_prompt, src, sty, ids)
        metrics["evaluated_on"] = evaluation_views(scene)
        from nerfart_plugin.systems.base import to_device

        dev = self.scene.device
        metrics["off_surface_weight"] = float(np.mean([off_surface_share(system.renderer, to_device(v, dev))
                                                       for v in views]))
        metrics["off_surface_weight_source"] = float(np.mean([off_surface_share(system.source, to_device(v, dev))
                                                              for v in views]))
        return metrics

    def save_heldout(self, ids: list[int], src: torch.Tensor, sty: torch.Tensor) -> None:
        """``heldout/source_<view>.png`` and ``heldout/stylized_<view>.png`` at the stylization resolution."""
        from PIL import Image

        from nerfart_plugin.export.video import to_uint8

        for i, a, b in zip(ids, src, sty):
            for name, img in (("source", a), ("stylized", b)):
                with atomic_path(self.folder.path / "heldout" / f"{name}_{int(i):04d}.png") as tmp:
                    Image.fromarray(to_uint8(img.permute(1, 2, 0))).save(tmp, format="PNG")

    @torch.no_grad()
    def video(self, system: Any) -> dict[str, Any]:
        """The source | stylized orbit video (``stylize.video_frames`` frames at the stylization size) and the
        view-consistency error along it; nothing with ``stylize.video_frames=0``."""
        from nerfart_plugin.data.camera_path import orbit_path
        from nerfart_plugin.data.rays import camera_batch
        from nerfart_plugin.evaluation import view_consistency
        from nerfart_plugin.export.video import side_by_side, to_uint8, write_video

        sc, stamp, scene = self.settings, self.style.stamp, self.scene.scene
        metrics: dict[str, Any] = {"view_consistency_error": None}
        if sc.video_frames <= 0:
            return metrics
        ref = self.scene.views(scene.train_ids[:1] or [0], sc.resolution)[0]
        c2ws = orbit_path(scene, sc.video_frames)
        K = scene.K[0].clone()
        K[0] *= ref["W"] / scene.width
        K[1] *= ref["H"] / scene.height
        near, far = float(scene.near.min()), float(scene.far.max())
        frames, sty_frames, src_frames = [], [], []
        label = "stylized" + (f" ({stamp.strip('_')})" if stamp else "")
        for c2w in c2ws:
            b = camera_batch(K, c2w, ref["H"], ref["W"], near, far, self.scene.ndc)
            a, s = system.render_batch(b, source=True), system.render_batch(b)
            src_frames.append(a)
            sty_frames.append(s)
            frames.append(side_by_side(to_uint8(a["rgb"]), to_uint8(s["rgb"]), labels=("source", label)))
        write_video(frames, self.folder.path / f"video{stamp}.mp4", fps=sc.video_fps)
        if not self.scene.ndc:  # NDC: depth is NDC t, warping not implemented: view_consistency_error stays None
            Kd = K.to(self.scene.device)
            metrics["view_consistency_error"] = view_consistency(sty_frames, Kd, c2ws)
            metrics["view_consistency_error_source"] = view_consistency(src_frames, Kd, c2ws)
        return metrics

    def compare_meshes(self, system: Any) -> dict[str, Any]:
        """``mesh/source``, ``mesh/stylized<stamp>``, ``mesh/displacement<stamp>.ply`` and the geometry change."""
        from nerfart_plugin.export.compare import compare_meshes, displacement_mesh, vertex_distances

        stamp, mesh_dir = self.style.stamp, self.folder.path / "mesh"
        src = export_source_mesh(self.scene, system.source.field, mesh_dir / "source",
                                 shared=Path(self.source).parent / "mesh" / "source")
        sty = export_mesh(self.scene, system.field, mesh_dir / f"stylized{stamp}")
        if src is None or sty is None:
            return {}
        sdf = system.source.field.signed_distance()
        m = compare_meshes(sty, src, n_samples=20_000, source_sdf=sdf)
        write_in_frame(self.scene, displacement_mesh(sty, vertex_distances(sty, src, source_sdf=sdf)),
                       mesh_dir / f"displacement{stamp}.ply")
        return {f"mesh_{k}": v for k, v in m.items()}


# ---------------------------------------------------------------------- export
def write_cameras(scene: SceneContext, folder: Path) -> None:
    """``cameras.json``: the capture's cameras in the frame of the run's meshes, for the viewer and
    ``stage=render`` (:meth:`~nerfart_plugin.data.camera_path.CaptureCameras.from_json`)."""
    from nerfart_plugin.data.camera_path import viewer_cameras

    atomic_write_json(folder / "cameras.json", viewer_cameras(scene.scene, scene.cfg.export.frame, scene.ndc))


def stylization_source(scene: SceneContext, recon: Optional[ReconstructStage]) -> tuple[Path, str]:
    """The checkpoint a stylization starts from and what identifies it in the stylization key: the cached
    reconstruction of these settings (its key covers the scene, data and render settings), or an explicit
    ``source_checkpoint``: its content, with the scene's content and the data and render settings, which
    the stylization uses too (a file that does not exist keeps its path; reading it fails clearly later)."""
    src = scene.cfg.source_checkpoint
    if src:
        path = Path(src)
        content = hash_files([path]) if path.is_file() else str(path.resolve())
        return path, config_hash({"checkpoint": content, **scene_settings(scene)})
    assert recon is not None
    return recon.folder.final, recon.key
