"""Stage 2: stylize a reconstructed NeRF toward a text prompt (NeRF-Art Sections 4.1-4.4).

Loss, Eq. 8:  L = λd·L_dir^r + λg·L_con^g + λl·L_con^l + λp·L_per + λr·L_reg
  * L_dir^r  Eq. 4, relative directional CLIP loss against the frozen source render
             (or Eq. 3, absolute, for the CLIP-NeRF-style ablation ``experiment=absolute_dir``);
  * L_con^g  Eq. 5/6, InfoNCE of the whole view vs. the target (positive) and sampled
             negative style prompts, τ = 0.07;
  * L_con^l  Eq. 5/6, the same on random local patches (1/10 of the view's AREA by default, as the
             official release: 112 px on 270x480), centred on the subject (the source render's opacity);
  * L_per    Eq. 9, VGG16 perceptual distance to the source render;
  * L_reg    Eq. 7, Σ_ij w_i w_j |d_i − d_j| on ray weights (suppresses cloudy geometry).
Each step renders one view without grad, takes dL/dI, and back-propagates it
through the field patch by patch at identical samples (Section 4.4,
:mod:`nerfart_plugin.rendering.two_pass`). Terms with λ = 0 are not computed.
SDF backbones also keep the eikonal term of the reconstruction
(``experiment.lambda_eikonal``, not part of Eq. 8) so that the moving surface
stays a distance field, as the official release does.

Geometry can move: the occupancy grid of the reconstruction is re-estimated
from the stylized field every ``stylize.occupancy_update_every`` steps, with
an SDF band of ``stylize.occupancy_band`` cells around the current surface,
so the surface is sampled wherever it goes (not only inside the source's
shell) and free space near it is sampled for Eq. 7 to act on.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from nerfart_plugin.data.rays import ndc_rays, pixel_rays
from nerfart_plugin.data.scene import Scene
from nerfart_plugin.guidance import NegativeSampler, random_patches
from nerfart_plugin.guidance.patches import subject_box
from nerfart_plugin.losses import (
    absolute_clip_loss,
    contrastive_loss,
    directional_clip_loss,
    perceptual_loss,
    silhouette_loss,
    weight_regularization,
)
from nerfart_plugin.rendering.two_pass import backprop_patches, render_fixed_samples
from nerfart_plugin.systems.base import RenderSystem, build_renderer, param_groups, step_seed, to_device
from nerfart_plugin.systems.callbacks import check_finite_grads, check_finite_losses
from nerfart_plugin.systems.scene_setup import SceneSetup

log = logging.getLogger(__name__)


def camera_batch(K: torch.Tensor, c2w: torch.Tensor, H: int, W: int, near: float, far: float,
                 ndc: bool) -> dict[str, Any]:
    """Ray batch of one camera (intrinsics ``K`` already at H x W), plus ints H, W."""
    o, d = pixel_rays(K, c2w, H, W)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    n = o.shape[0]
    if ndc:
        o, d = ndc_rays(o, d, K, 1.0, H=H, W=W)
        near, far = 0.0, 1.0
    return {"rays_o": o.float(), "rays_d": d.float(), "near": torch.full((n,), float(near)),
            "far": torch.full((n,), float(far)), "H": int(H), "W": int(W)}


def style_views(scene: Scene, ids: list[int], resolution: int, ndc: bool) -> list[dict[str, Any]]:
    """Ray batches of views ``ids`` with the long side resized to ``resolution`` pixels."""
    s = resolution / max(scene.height, scene.width)
    H, W = max(1, round(scene.height * s)), max(1, round(scene.width * s))
    views = []
    for i in ids:
        K = scene.K[i].clone()
        K[0] *= W / scene.width
        K[1] *= H / scene.height
        b = camera_batch(K, scene.c2w[i], H, W, float(scene.near[i]), float(scene.far[i]), ndc)
        b["view_id"] = int(i)
        views.append(b)
    return views


class StylizationSystem(RenderSystem):
    """Fine-tunes a copy of the reconstructed field; the frozen source gives I_src.

    Args:
        cfg: the ``stylize`` config; experiment: λ weights and the directional mode.
        backbone_cfg / encoding_cfg / render_cfg / setup: as for reconstruction (the
            field must have the same architecture as the source checkpoint).
        source_state: state dict of the reconstruction's renderer.
        views: training view ray batches at the stylization resolution (:func:`style_views`).
        guidance / perceptual: frozen encoders (not saved in checkpoints).
        prompt / source_prompt: target text (after augmentation) and source text.
        negatives: negative style prompts, plain or ``(category, prompt)`` pairs
            (:func:`nerfart_plugin.guidance.prompts.resolve_negatives`).
        seed: run seed. out_dir: run folder. stamp: suffix for file names
            (e.g. ``_UNSTYLED-toy`` when the guidance is not a real CLIP).
        raw_prompt: the prompt as typed (before augmentation), for the negatives' exclusion rules.
    """

    stage = "stylize"

    def __init__(self, cfg: dict, experiment: dict, backbone_cfg: dict, encoding_cfg: dict, render_cfg: dict,
                 setup: SceneSetup, source_state: dict, views: list[dict], guidance: Any, perceptual: Any,
                 prompt: str, source_prompt: str, negatives: list, seed: int = 0,
                 out_dir: Optional[str] = None, stamp: str = "", raw_prompt: Optional[str] = None) -> None:
        super().__init__()
        self.automatic_optimization = False
        self.cfg, self.exp = dict(cfg), dict(experiment)
        self.setup_info = setup
        self.renderer = build_renderer(backbone_cfg, encoding_cfg, render_cfg, setup)
        self.remember_model(backbone_cfg, encoding_cfg, setup)
        self.renderer.load_state_dict(source_state)
        source = build_renderer(backbone_cfg, encoding_cfg, render_cfg, setup)
        source.load_state_dict(source_state)
        source.requires_grad_(False).eval()
        # The reconstruction's occupancy grid already concentrates samples at the surface, so the
        # stylization stage can afford fewer samples per ray (stylize.num_samples; null: as rendered).
        if self.cfg.get("num_samples"):
            self.renderer.num_samples = source.num_samples = int(self.cfg["num_samples"])
        # Frozen helpers live outside the module tree: not trained, not checkpointed.
        self._frozen = {"source": source, "guidance": guidance, "perceptual": perceptual}
        self.views = views
        self.prompt, self.source_prompt = prompt, source_prompt
        self.negatives = negatives
        self.raw_prompt = raw_prompt or prompt
        self.seed = int(seed)
        self.out_dir = Path(out_dir) if out_dir else None
        self.stamp = stamp
        self.total_steps = int(self.cfg.get("steps", 100))
        self.freeze_geometry = bool(self.cfg.get("freeze_geometry", False))
        if self.freeze_geometry:
            for p in self.field.geometry_parameters():
                p.requires_grad_(False)
        self.lambdas = {
            "dir": float(self.exp.get("lambda_dir", 1.0)),
            "global": float(self.exp.get("lambda_global", 0.2)),
            # stylize.local_patches=0: no local patches, so no local term
            "local": float(self.exp.get("lambda_local", 0.1)) if int(self.cfg.get("local_patches", 4)) > 0 else 0.0,
            "perceptual": float(self.exp.get("lambda_perceptual", 2.0)),
            "reg": float(self.exp.get("lambda_reg", 0.1)),
            "eikonal": (float(self.exp.get("lambda_eikonal", 0.1))
                        if self.field.is_sdf and not self.freeze_geometry else 0.0),
            "silhouette": 0.0 if self.freeze_geometry else float(self.exp.get("lambda_silhouette", 0.0)),
        }
        occ = self.renderer.occupancy
        self.occupancy_every = 0 if self.freeze_geometry or occ is None else int(self.cfg.get("occupancy_update_every", 8))
        if self.occupancy_every > 0:  # the SDF band the moving surface is sampled in (world units)
            occ.sdf_band = max(occ.sdf_band, float(self.cfg.get("occupancy_band", 3.0)) * occ.cell_size)
        self._cache: dict[int, dict[str, Any]] = {}
        self.timings: dict[str, float] = {}

    # ------------------------------------------------------------------ frozen parts
    @property
    def source(self):
        return self._frozen["source"]

    @property
    def guidance(self):
        return self._frozen["guidance"]

    @property
    def perceptual(self):
        return self._frozen["perceptual"]

    def on_fit_start(self) -> None:
        for m in self._frozen.values():
            m.to(self.device)
        g = self.guidance
        self.tgt_txt = g.encode_text([self.prompt])[0]
        ids = np.linspace(0, len(self.views) - 1, min(8, len(self.views))).round().astype(int).tolist()
        src_imgs = torch.cat([self.source_view(i)["img"] for i in dict.fromkeys(ids)])
        self.src_txt = g.source_embedding(self.source_prompt, src_imgs)
        self.neg_sampler = None
        if self.lambdas["global"] > 0 or self.lambdas["local"] > 0:
            threshold = self.cfg.get("negative_threshold")
            self.neg_sampler = NegativeSampler(g, self.negatives, self.prompt,
                                               threshold=None if threshold in (None, "auto") else float(threshold),
                                               num_per_step=int(self.cfg.get("num_negatives", 64)),
                                               raw_prompt=self.raw_prompt)

    @torch.no_grad()
    def source_view(self, i: int) -> dict[str, Any]:
        """Cached I_src of view ``i`` ([1,3,H,W]), its guidance embedding, perceptual features and the
        subject's bounding box (source opacity > 0.5; None if the view shows nothing)."""
        if i not in self._cache:
            v = self.views[i]
            out = self.source.render_chunked(to_device(v, self.device), chunk=int(self.cfg.get("chunk", 4096)),
                                             with_normals=False)
            img = out["rgb"].reshape(v["H"], v["W"], 3).permute(2, 0, 1)[None].clamp(0, 1)
            entry = {"img": img, "emb": self.guidance.encode_image(img), "opacity": out["opacity"],
                     "box": subject_box(out["opacity"].reshape(v["H"], v["W"]))}
            if self.lambdas["perceptual"] > 0:
                entry["feats"] = [f.detach() for f in self.perceptual.features(img)]
            self._cache[i] = entry
        return self._cache[i]

    def view_for_step(self, step: int) -> int:
        """A fresh random permutation of the views every epoch, a function of (seed, step) only."""
        n = len(self.views)
        g = torch.Generator().manual_seed(step_seed(self.seed, step // n))
        return int(torch.randperm(n, generator=g)[step % n])

    # ------------------------------------------------------------------ losses on the image
    def image_losses(self, img: torch.Tensor, src: dict[str, Any], g: torch.Generator) -> dict[str, torch.Tensor]:
        """The image terms of Eq. 8 for the rendered view ``img`` [1,3,H,W] (λ=0 terms skipped)."""
        lam, terms = self.lambdas, {}
        need_emb = lam["dir"] > 0 or lam["global"] > 0
        need_local = self.neg_sampler is not None and lam["local"] > 0
        inputs = [img] if need_emb else []
        if need_local:  # Eq. 6: random patches of local_patch_frac of the view's area, on the subject
            inputs.append(random_patches(img, int(self.cfg.get("local_patches", 4)),
                                         float(self.cfg.get("local_patch_frac", 0.1)),
                                         self.guidance.input_size, generator=g, region=src["box"]))
        encoded = self.guidance.encode_images(inputs) if inputs else []  # one CLIP pass for view + patches
        emb = encoded[0] if need_emb else None
        if lam["dir"] > 0:
            if self.exp.get("directional", "relative") == "absolute":
                terms["dir"] = absolute_clip_loss(emb, self.tgt_txt)  # Eq. 3
            else:
                terms["dir"] = directional_clip_loss(emb, src["emb"], self.tgt_txt, self.src_txt)  # Eq. 4
        if self.neg_sampler is not None:
            _, negs = self.neg_sampler.sample(g)
            tau = float(self.cfg.get("tau", 0.07))
            if lam["global"] > 0:
                terms["global"] = contrastive_loss(emb, self.tgt_txt, negs, tau)  # Eq. 5, global
            if need_local:
                terms["local"] = contrastive_loss(encoded[-1], self.tgt_txt, negs, tau)  # Eq. 5 on patches
        if lam["perceptual"] > 0:
            terms["perceptual"] = perceptual_loss(self.perceptual.features(img), src["feats"])  # Eq. 9
        return terms

    # ------------------------------------------------------------------ one step
    def training_step(self, _: Any, batch_idx: int) -> None:
        step = self.global_step
        opt = self.optimizers()
        self.field.update_step(step, self.total_steps)
        g = torch.Generator().manual_seed(step_seed(self.seed, step))
        torch.manual_seed(step_seed(self.seed, step) + 1)
        self.follow_geometry(step)
        i = self.view_for_step(step)
        view = to_device(self.views[i], self.device)
        H, W = view["H"], view["W"]
        t0 = time.perf_counter()
        src = self.source_view(i)
        t1 = time.perf_counter()

        # pass 1: the full view without grad, samples fixed for this step
        first = render_fixed_samples(self.renderer, view, int(self.cfg.get("chunk", 4096)), perturb=True)
        t2 = time.perf_counter()
        img = first["rgb"].reshape(H, W, 3).permute(2, 0, 1)[None].clone().requires_grad_(True)
        terms = self.image_losses(img, src, g)
        check_finite_losses(terms, step, "stylize")
        image_loss = sum(self.lambdas[k] * v for k, v in terms.items())
        rgb_grad = torch.autograd.grad(image_loss, img)[0][0].permute(1, 2, 0).reshape(-1, 3) if terms else torch.zeros_like(first["rgb"])
        t3 = time.perf_counter()

        # pass 2: re-render patches with grad at the same samples, back-propagate dL/dI (+ Eq. 7)
        opt.zero_grad(set_to_none=True)
        ray_losses = {
            "reg": (self.lambdas["reg"], lambda out, rays: weight_regularization(out["weights"], out["t"])),
            "eikonal": (self.lambdas["eikonal"], lambda out, rays: out["eikonal"]),
            "silhouette": (self.lambdas["silhouette"],
                           lambda out, rays: silhouette_loss(out["opacity"], rays["source_opacity"])),
        }
        if self.lambdas["silhouette"] > 0:
            view = {**view, "source_opacity": src["opacity"]}
        patch = int(self.cfg.get("patch_size", 64))
        ray_terms = backprop_patches(self.renderer, view, first["t_samples"], rgb_grad, patch * patch,
                                     ray_losses, backward=self.manual_backward)
        check_finite_grads(self, step)
        opt.step()
        t4 = time.perf_counter()

        total = float(image_loss.detach()) if terms else 0.0
        total += sum(self.lambdas[k] * v for k, v in ray_terms.items())
        for k, v in terms.items():
            self.log(f"train/loss_{k}", v.detach(), prog_bar=(k == "dir"))
        for k, v in ray_terms.items():
            self.log(f"train/loss_{k}", v)
        self.log("train/loss", total, prog_bar=True)
        self.timings = {"source_cache": t1 - t0, "render_nograd": t2 - t1, "losses_and_image_grad": t3 - t2,
                        "patch_backprop": t4 - t3, "step": t4 - t0}
        self.log("step_s", t4 - t0, prog_bar=True)
        every = int(self.cfg.get("render_every", 25))
        if self.out_dir is not None and every > 0 and (step % every == 0 or step + 1 == self.total_steps):
            from nerfart_plugin.systems.reconstruction import to_image
            from nerfart_plugin.export.video import save_image_grid

            pair = [to_image(src["img"][0].permute(1, 2, 0)), to_image(img.detach()[0].permute(1, 2, 0))]
            save_image_grid(pair, self.out_dir / "renders" / f"step_{step:05d}{self.stamp}.png")

    @torch.no_grad()
    def follow_geometry(self, step: int) -> bool:
        """Re-estimate the occupancy grid from the stylized field every ``occupancy_update_every`` steps
        (all cells), so rays find the surface wherever the stylization moves it. Returns True if updated."""
        if self.occupancy_every <= 0 or step % self.occupancy_every:
            return False
        return self.renderer.occupancy.update(self.field, step, force=True)

    def configure_optimizers(self) -> Any:
        lr, lr_mlp = float(self.cfg.get("lr", 2e-3)), float(self.cfg.get("lr_mlp", 5e-4))
        groups = param_groups(self.renderer, lr, lr_mlp, geometry=not self.freeze_geometry)
        return torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15)

    # ------------------------------------------------------------------ rendering for outputs
    @torch.no_grad()
    def render_batch(self, batch: dict[str, Any], source: bool = False) -> dict[str, torch.Tensor]:
        r = self.source if source else self.renderer
        out = r.render_chunked(to_device(batch, self.device), chunk=int(self.cfg.get("chunk", 4096)))
        H, W = batch["H"], batch["W"]
        return {k: v.reshape(H, W, -1) for k, v in out.items() if torch.is_tensor(v)}


def image_to_uint8(img: torch.Tensor) -> np.ndarray:
    return (img.detach().float().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
