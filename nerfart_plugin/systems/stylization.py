"""Stage 2: stylize a reconstructed NeRF toward a text prompt (NeRF-Art Sections 4.1-4.4), a style picture, or both.

Loss, Eq. 8:  L = λd·L_dir^r + λg·L_con^g + λl·L_con^l + λp·L_per + λr·L_reg
  * L_dir^r  Eq. 4, relative directional CLIP loss against the frozen source render
             (or Eq. 3, absolute, for the CLIP-NeRF-style ablation ``experiment=absolute_dir``);
  * L_con^g  Eq. 5/6, InfoNCE of the whole view vs. the target (positive) and sampled
             negative style prompts, τ = 0.07;
  * L_con^l  Eq. 5/6, the same on random local patches (1/10 of the view's AREA by default, as the
             official release: 112 px on 270x480), centred on the subject (the source render's opacity);
  * L_per    Eq. 9, VGG16 perceptual distance to the source render;
  * L_reg    Eq. 7, Σ_ij w_i w_j |d_i − d_j| on ray weights (suppresses cloudy geometry).
With a style picture (``style_image``) two terms join them, after ARF (Zhang et al. 2022):
  * L_style  nearest-neighbour feature matching of the view's features (the subject's pixels) to the picture's;
  * L_pal    the view's local colours pulled toward the source view recoloured to the picture's palette;
the text terms drop out when no prompt is given; L_per (to the source) keeps the subject recognisable.
Each term is one row of :data:`~nerfart_plugin.systems.stylization_losses.STYLIZATION_IMAGE_LOSSES` (on the rendered
view) or :data:`~nerfart_plugin.systems.stylization_losses.STYLIZATION_RAY_LOSSES` (per ray, with grad), weighted by ``experiment.lambda_<name>``.
Each step renders one view without grad, takes dL/dI, and back-propagates it
through the field patch by patch at identical samples (Section 4.4,
:mod:`nerfart_plugin.rendering.two_pass`); ``stylize.backprop=retain`` renders the view
once with grad and back-propagates through its kept graph instead (the same gradient,
more memory, no re-render). Terms with λ = 0 are not computed.
The field's regularizers join the ray terms (:mod:`nerfart_plugin.systems.loss_terms`):
SDF backbones keep the eikonal term of the reconstruction (``experiment.lambda_eikonal``,
not part of Eq. 8) so that the moving surface stays a distance field, as the official
release does.

Geometry can move: the occupancy grid of the reconstruction is re-estimated
from the stylized field every ``stylize.occupancy_update_every`` steps, with
an SDF band of ``stylize.occupancy_band`` cells around the current surface,
so the surface is sampled wherever it goes (not only inside the source's
shell) and free space near it is sampled for Eq. 7 to act on.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch
from torch import Tensor

from nerfart_plugin.config.schema import MAX_GRAD_SAMPLES, StylizeConfig
from nerfart_plugin.config.validate import section
from nerfart_plugin.data.setup import SceneSetup
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.guidance import NegativeSampler, random_patches
from nerfart_plugin.fields.composite import CompositeField, RegionMask
from nerfart_plugin.rendering import VolumeRenderer
from nerfart_plugin.guidance.patches import subject_box
from nerfart_plugin.guidance.style import Style, negatives_of
from nerfart_plugin.guidance.style_image import match_palette
from nerfart_plugin.rendering.two_pass import (backprop_patches, backprop_retained, render_fixed_samples,
    render_with_graph)
from nerfart_plugin.systems.base import RenderSystem, adam, build_renderer, param_groups, step_seed
from nerfart_plugin.systems.callbacks import check_finite_grads
from nerfart_plugin.systems.loggers import log_images
from nerfart_plugin.systems.loss_terms import compute, regularizer_weights, weighted_sum, weights_of
from nerfart_plugin.systems.stylization_losses import (STYLE_IMAGE_LOSSES, STYLIZATION_IMAGE_LOSSES,
    STYLIZATION_RAY_LOSSES, ImageInputs, regularizer_term)
from nerfart_plugin.utils.device import to_device
from nerfart_plugin.utils.images import image_grid, save_image, to_uint8

log = logging.getLogger(__name__)


@dataclass
class ImagePass:
    """What pass 1 of a step hands to pass 2.

    Attributes:
        render: the view's render without grad (``rgb`` [H*W,3], ``t_samples``: the samples pass 2 re-renders).
        graph: with ``stylize.backprop=retain``, the render's chunks with their graph kept; else None.
        img: the view [1,3,H,W] the image losses saw; terms: their values; loss: their weighted sum.
        rgb_grad: dL/dI [H*W,3]; rendered_at: ``time.perf_counter()`` when the render was done.
    """

    render: dict[str, Any]
    graph: Optional[Any]
    img: Tensor
    terms: dict[str, Tensor]
    loss: Tensor
    rgb_grad: Tensor
    rendered_at: float


class StylizationSystem(RenderSystem):
    """Fine-tunes a copy of the reconstructed field; the frozen source gives I_src.

    Args:
        cfg: the ``stylize`` section; experiment: the ``experiment`` section (λ weights, directional mode);
            each a typed section or a dict of its keys (the rest: the schema's defaults).
        backbone_cfg / encoding_cfg / render_cfg / setup: as for reconstruction (the
            field must have the same architecture as the source checkpoint).
        source_state: state dict of the reconstruction's renderer.
        views: training view ray batches at the stylization resolution
            (:func:`nerfart_plugin.data.rays.views_at_resolution`).
        guidance / perceptual: frozen encoders (not saved in checkpoints).
        prompt / source_prompt: target text (after augmentation) and source text.
        negatives: negative style prompts, plain or ``(category, prompt)`` pairs
            (:func:`nerfart_plugin.guidance.prompts.resolve_negatives`).
        seed: run seed. out_dir: run folder. stamp: suffix for file names
            (e.g. ``_UNSTYLED-toy`` when the guidance is not a real CLIP).
        raw_prompt: the prompt as typed (before augmentation), for the negatives' exclusion rules.
    """

    stage = "stylize"

    def __init__(self, cfg: Any, setup: SceneSetup, style: Style, source_state: dict, views: list[dict],
                 settings: Optional[StylizeConfig | dict] = None, out_dir: Optional[str] = None,
                 region: Optional[RegionMask] = None) -> None:
        """``cfg``: the run's config (its ``experiment``, ``backbone``, ``encoding``, ``render`` and ``seed``;
        see :class:`~nerfart_plugin.systems.base.RenderSystem`); ``style``: the guide, perceptual network and
        prompts (:func:`~nerfart_plugin.guidance.style.build_style`); ``source_state``: the reconstruction's
        renderer tensors; ``views``: the training views' ray batches at the stylization's resolution;
        ``settings``: the ``stylize`` section with its ``auto`` settings resolved (default ``cfg.stylize``);
        ``region``: stylize only inside it (bound to the field's frame): every render of the stylization is then
        the source with the stylized field composed in the region (:class:`~nerfart_plugin.fields.composite.CompositeField`),
        the source's own outside."""
        super().__init__(cfg, setup)
        self.automatic_optimization = False
        c = self.run_cfg
        self.cfg = section(StylizeConfig, c.stylize if settings is None else settings)
        self.exp = c.experiment
        self.renderer.load_state_dict(source_state)
        source = build_renderer(c, self.setup_info)
        source.load_state_dict(source_state)
        source.requires_grad_(False).eval()
        # The reconstruction's occupancy grid already concentrates samples at the surface, so the
        # stylization stage can afford fewer samples per ray (stylize.num_samples; null: as rendered);
        # without a grid (NDC captures) the uniform samples stay at the reconstruction's density.
        # Its views (source images, held-out renders, video) use the samples it stylizes with.
        if not (self.renderer.reduce_samples(self.cfg.num_samples) and source.reduce_samples(self.cfg.num_samples)) \
                and self.cfg.num_samples:
            log.info("stylize.num_samples=%d ignored: no occupancy grid places the samples, so the stylization "
                     "keeps render.num_samples=%d", self.cfg.num_samples, self.renderer.num_samples)
        # Frozen helpers live outside the module tree: not trained, not checkpointed.
        self._frozen = {"source": source, "guidance": style.guidance, "perceptual": style.perceptual,
                        "style_features": style.features}
        self.style_image = style.image
        if region is not None:  # what renders: the composite, on the stylized renderer's own occupancy grid
            composite = CompositeField(source.field, [(self.renderer.field, 1.0, region)])
            self._frozen["view"] = self.renderer.with_field(composite, share_occupancy=True)
            if self.renderer.occupancy is not None:  # outside the region the source's cells, as they are
                self.renderer.occupancy.keep.copy_(composite.cells_outside(self.renderer.occupancy))
        self.views = views
        self.prompt, self.source_prompt, self.raw_prompt = style.prompt, style.source_prompt, style.raw_prompt
        self.negatives = negatives_of(style, self.cfg.negatives)
        self.seed = int(c.seed)
        self.out_dir = Path(out_dir) if out_dir else None
        self.stamp = style.stamp
        self.total_steps = self.cfg.steps
        self.freeze_geometry = self.cfg.freeze_geometry
        if self.freeze_geometry:
            for p in self.field.geometry_parameters():
                p.requires_grad_(False)
        self._init_loss_weights()
        self._check_retained_graph_fits()
        self.occupancy_every = 0 if self.freeze_geometry else self.cfg.occupancy_update_every
        if self.occupancy_every > 0:  # the SDF band the moving surface is sampled in
            self.view.widen_occupancy_band(self.cfg.occupancy_band)
        # set by on_fit_start (they need the guidance on the training device)
        self.tgt_txt: Optional[Tensor] = None
        self.src_txt: Optional[Tensor] = None
        self.neg_sampler: Optional[NegativeSampler] = None
        self.style_feats: list[Tensor] = []
        self._cache: dict[int, dict[str, Any]] = {}
        self.timings: dict[str, float] = {}

    def _check_retained_graph_fits(self) -> None:
        """``stylize.backprop=retain`` keeps a view's whole graph: refuse views whose samples (rays x samples
        per ray) exceed what one step with grad may hold (:data:`nerfart_plugin.config.schema.MAX_GRAD_SAMPLES`)."""
        if self.cfg.backprop != "retain" or not self.views:
            return
        rays = max(int(v["rays_o"].shape[0]) for v in self.views)
        samples = rays * self.renderer.num_samples
        if samples > MAX_GRAD_SAMPLES:
            raise ConfigError(f"stylize.backprop=retain keeps the graph of a whole view: {rays:,} rays x "
                              f"{self.renderer.num_samples} samples = {samples:,} samples, more than the "
                              f"{MAX_GRAD_SAMPLES:,} one step with grad may hold; use stylize.backprop=patch (the "
                              "paper's, memory bounded by stylize.patch_size) or a lower stylize.resolution")

    def _init_loss_weights(self) -> None:
        geometry_off = [t.name for t in STYLIZATION_RAY_LOSSES if t.geometry] if self.freeze_geometry else []
        local_off = ["local"] if self.cfg.local_patches == 0 else []  # no local patches, no local term
        text_off = [] if self.prompt is not None else ["dir", "global", "local"]  # a picture alone
        picture_off = [] if self.style_image is not None else [t.name for t in STYLE_IMAGE_LOSSES]
        self.lambdas = {**weights_of(STYLIZATION_IMAGE_LOSSES, self.exp, off=local_off + text_off),
                        **weights_of(STYLE_IMAGE_LOSSES, self.run_cfg.style_image, off=picture_off),
                        **weights_of(STYLIZATION_RAY_LOSSES, self.exp, off=geometry_off)}
        self.reg_lambdas = regularizer_weights(self.field.regularizer_names, self.exp, off=self.freeze_geometry)

    # ------------------------------------------------------------------ frozen parts
    @property
    def source(self):
        """The frozen source renderer (I_src)."""
        return self._frozen["source"]

    @property
    def view(self) -> VolumeRenderer:
        """What renders the stylization: the composite inside a region, else the stylized renderer itself."""
        return self._frozen.get("view", self.renderer)

    @property
    def guidance(self):
        """The text guide (None for a style picture alone)."""
        return self._frozen["guidance"]

    @property
    def style_features(self):
        """The network whose features are matched to the style picture (None without one)."""
        return self._frozen["style_features"]

    @property
    def perceptual(self):
        return self._frozen["perceptual"]

    @property
    def contrastive(self) -> bool:
        """Whether a contrastive term (Eq. 5) is on, i.e. negatives are sampled."""
        return self.lambdas["global"] > 0 or self.lambdas["local"] > 0

    def on_fit_start(self) -> None:
        self.prepare_text()

    @torch.no_grad()
    def prepare_text(self) -> None:
        """Move the frozen parts to the device; the style picture's features; the target / source text
        embeddings and the negatives."""
        for m in self._frozen.values():
            if m is not None:
                m.to(self.device)
        if self.style_image is not None:
            self.style_feats = [f.detach() for f in self.style_features.features(self.style_image.image[None].to(self.device))]
        self.neg_sampler = None
        if self.prompt is None:
            return
        g = self.guidance
        self.tgt_txt = g.encode_text([self.prompt])[0]
        ids = np.linspace(0, len(self.views) - 1, min(8, len(self.views))).round().astype(int).tolist()
        src_imgs = torch.cat([self.source_view(i)["img"] for i in dict.fromkeys(ids)])
        self.src_txt = g.source_embedding(self.source_prompt, src_imgs)
        if self.contrastive:
            threshold = self.cfg.negative_threshold
            self.neg_sampler = NegativeSampler(g, self.negatives, self.prompt,
                                               threshold=None if threshold == "auto" else float(threshold),
                                               num_per_step=self.cfg.num_negatives, raw_prompt=self.raw_prompt)

    def negatives_report(self) -> dict[str, Any]:
        """``negatives_kept`` and ``negatives_excluded`` (prompt, reason) for ``metrics.json``."""
        if self.neg_sampler is None:
            return {"negatives_kept": 0, "negatives_excluded": []}
        return {"negatives_kept": len(self.neg_sampler),
                "negatives_excluded": [{"prompt": n, "reason": r} for n, r in self.neg_sampler.excluded]}

    @torch.no_grad()
    def source_view(self, i: int) -> dict[str, Any]:
        """Cached I_src of view ``i`` ([1,3,H,W]), its guidance embedding (with a prompt), perceptual features,
        the subject's bounding box (source opacity > 0.5; None if the view shows nothing) and, with a style
        picture, the subject's mask [H,W] and the view recoloured to the picture's palette [1,3,H,W]."""
        if i not in self._cache:
            v = self.views[i]
            out = self.source.render_chunked(to_device(v, self.device), chunk=self.cfg.chunk, with_normals=False)
            img = out["rgb"].reshape(v["H"], v["W"], 3).permute(2, 0, 1)[None].clamp(0, 1)
            entry = {"img": img, "opacity": out["opacity"], "box": self._patch_box(v, out),
                     "mask": out["opacity"].reshape(v["H"], v["W"]).float()}
            if self.guidance is not None:
                entry["emb"] = self.guidance.encode_image(img)
            if self.lambdas["perceptual"] > 0:
                entry["feats"] = [f.detach() for f in self.perceptual.features(img)]
            if self.lambdas["palette"] > 0:
                entry["palette"] = match_palette(img[0], self.style_image.image, entry["mask"] > 0.5)[None]
            self._cache[i] = entry
        return self._cache[i]

    def _patch_box(self, view: dict[str, Any], out: dict[str, Tensor]) -> Optional[tuple[int, int, int, int]]:
        """Where a view's local patches are drawn: the subject's box (source opacity > 0.5), inside a region the
        box of the subject's visible surface within it (its colour mask > 0.5 at the source's depth), so the
        local terms look at what may change; the subject's box when the view does not see the region."""
        H, W = int(view["H"]), int(view["W"])
        opacity = out["opacity"].reshape(H, W)
        composite = self._frozen.get("view")
        if composite is None:
            return subject_box(opacity)
        rays_o, rays_d = view["rays_o"].to(self.device), view["rays_d"].to(self.device)
        colour, _ = composite.field.regions[0](rays_o + rays_d * out["depth"].reshape(-1, 1))
        inside = subject_box(opacity * colour.reshape(H, W))
        return inside if inside is not None else subject_box(opacity)

    def view_for_step(self, step: int) -> int:
        """A fresh random permutation of the views every epoch, a function of (seed, step) only."""
        n = len(self.views)
        g = torch.Generator().manual_seed(step_seed(self.seed, step // n))
        return int(torch.randperm(n, generator=g)[step % n])

    # ------------------------------------------------------------------ losses on the image
    def image_inputs(self, img: Tensor, src: dict[str, Any], g: torch.Generator) -> ImageInputs:
        """The shared inputs of the image terms: one guidance pass for the view and its local patches
        (Eq. 6: random patches of ``local_patch_frac`` of the view's area, on the subject), then the negatives."""
        lam = self.lambdas
        need_emb, need_local = lam["dir"] > 0 or lam["global"] > 0, lam["local"] > 0
        inputs = [img] if need_emb else []
        if need_local:
            inputs.append(random_patches(img, self.cfg.local_patches, self.cfg.local_patch_frac,
                                         self.guidance.input_size, generator=g, region=src["box"]))
        encoded = self.guidance.encode_images(inputs) if inputs else []
        x = ImageInputs(img, src, emb=encoded[0] if need_emb else None, patch_emb=encoded[-1] if need_local else None)
        if self.neg_sampler is not None:
            x.negs = self.neg_sampler.sample(g)[1]
        return x

    def image_losses(self, img: Tensor, src: dict[str, Any], g: torch.Generator) -> dict[str, Tensor]:
        """The image terms of Eq. 8 and the style picture's for the rendered view ``img`` [1,3,H,W] (λ=0 terms
        skipped)."""
        return compute(STYLIZATION_IMAGE_LOSSES + STYLE_IMAGE_LOSSES, self.lambdas, self,
                       self.image_inputs(img, src, g))

    def ray_losses(self) -> dict[str, tuple[float, Any]]:
        """``name -> (λ, fn(render_out, rays))`` of the per-ray terms and the field's regularizers."""
        terms = {t.name: (self.lambdas[t.name], t.fn) for t in STYLIZATION_RAY_LOSSES}
        terms.update({n: (w, regularizer_term(n)) for n, w in self.reg_lambdas.items()})
        return terms

    # ------------------------------------------------------------------ one step
    def training_step(self, _: Any, batch_idx: int) -> None:
        step = self.global_step
        self.field.update_step(step, self.total_steps)
        g = torch.Generator().manual_seed(step_seed(self.seed, step))
        torch.manual_seed(step_seed(self.seed, step) + 1)
        self.follow_geometry(step)
        i = self.view_for_step(step)
        view = to_device(self.views[i], self.device)
        t0 = time.perf_counter()
        src = self.source_view(i)
        t1 = time.perf_counter()
        first = self.image_pass(view, src, g, step)
        t3 = time.perf_counter()
        ray_losses = self.ray_losses()
        ray_terms = self.patch_pass(view, src, first, ray_losses, step)
        t4 = time.perf_counter()
        total = float(first.loss.detach()) if first.terms else 0.0
        total += sum(ray_losses[k][0] * v for k, v in ray_terms.items())
        self._log_step(first.terms, ray_terms, total, (t0, t1, first.rendered_at, t3, t4))
        self._save_render(step, src, first.img)

    def image_pass(self, view: dict[str, Any], src: dict[str, Any], g: torch.Generator, step: int) -> "ImagePass":
        """Pass 1: the full view at samples fixed for this step (without grad; ``stylize.backprop=retain``:
        with grad, the render's graph kept), the image terms and dL/dI (:class:`ImagePass`)."""
        H, W = view["H"], view["W"]
        graph = None
        if self.cfg.backprop == "retain":
            first, graph = render_with_graph(self.view, view, self.cfg.chunk, perturb=True)
        else:
            first = render_fixed_samples(self.view, view, self.cfg.chunk, perturb=True)
        t_render = time.perf_counter()
        img = first["rgb"].reshape(H, W, 3).permute(2, 0, 1)[None].clone().requires_grad_(True)
        terms = self.image_losses(img, src, g)
        image_loss = weighted_sum(terms, self.lambdas, step, "stylize")
        with torch.autocast(img.device.type, enabled=False):  # backward ops in their forward dtypes (two_pass)
            rgb_grad = (torch.autograd.grad(image_loss, img)[0][0].permute(1, 2, 0).reshape(-1, 3) if terms
                        else torch.zeros_like(first["rgb"]))
        return ImagePass(first, graph, img, terms, image_loss, rgb_grad, t_render)

    def patch_pass(self, view: dict[str, Any], src: dict[str, Any], first: "ImagePass",
                   ray_losses: dict[str, tuple[float, Any]], step: int) -> dict[str, float]:
        """Pass 2: re-render patches with grad at the samples of pass 1 (or, with ``stylize.backprop=retain``,
        use the graph it kept), back-propagate dL/dI and the ray terms, then one optimizer step. Returns each
        ray term's value (mean over the view's rays)."""
        opt = self.optimizers()
        opt.zero_grad(set_to_none=True)
        if self.lambdas["silhouette"] > 0:
            view = {**view, "source_opacity": src["opacity"]}
        if first.graph is not None:
            graph, first.graph = first.graph, None  # freed with the backward
            ray_terms = backprop_retained(graph, view, first.rgb_grad, ray_losses, backward=self.manual_backward)
        else:
            ray_terms = backprop_patches(self.view, view, first.render["t_samples"], first.rgb_grad,
                                         self.cfg.patch_size ** 2, ray_losses, backward=self.manual_backward)
        check_finite_grads(self, step)
        opt.step()
        return ray_terms

    def _save_render(self, step: int, src: dict[str, Any], img: Tensor) -> None:
        """``renders/step_<step><stamp>.png`` (source | stylized) every ``stylize.render_every`` steps and at the end."""
        every = self.cfg.render_every
        if self.out_dir is None or every <= 0 or not (step % every == 0 or step + 1 == self.total_steps):
            return


        pair = [to_uint8(src["img"][0].permute(1, 2, 0)), to_uint8(img.detach()[0].permute(1, 2, 0))]
        grid = image_grid(pair)
        save_image(grid, self.out_dir / "renders" / f"step_{step:05d}{self.stamp}.png")
        log_images(self.loggers, "renders/source|stylized", [grid], step)

    def _log_step(self, terms: dict[str, Tensor], ray_terms: dict[str, float], total: float, t: tuple) -> None:
        for k, v in terms.items():
            self.log(f"train/loss_{k}", v.detach(), prog_bar=(k == "dir"))
        for k, v in ray_terms.items():
            self.log(f"train/loss_{k}", v)
        self.log("train/loss", total, prog_bar=True)
        t0, t1, t2, t3, t4 = t
        self.timings = {"source_cache": t1 - t0, "render_nograd": t2 - t1, "losses_and_image_grad": t3 - t2,
                        "patch_backprop": t4 - t3, "step": t4 - t0}
        self.log("step_s", t4 - t0, prog_bar=True)

    @torch.no_grad()
    def follow_geometry(self, step: int) -> bool:
        """Re-estimate the occupancy grid from the stylized field every ``occupancy_update_every`` steps
        (all cells), so rays find the surface wherever the stylization moves it. Returns True if updated."""
        if self.occupancy_every <= 0 or step % self.occupancy_every:
            return False
        return self.view.update_occupancy(step, force=True)

    def configure_optimizers(self) -> Any:
        groups = param_groups(self.renderer, self.cfg.lr, self.cfg.lr_mlp, geometry=not self.freeze_geometry)
        return adam(groups)

    # ------------------------------------------------------------------ rendering for outputs
    @torch.no_grad()
    def render_batch(self, batch: dict[str, Any], source: bool = False) -> dict[str, Tensor]:
        """A full view of the stylized (or, ``source=True``, the source) field -> rgb, depth and opacity
        images [H,W,C] (no normals: an SDF's normal costs a gradient of the field per sample)."""
        return self.render_view(batch, chunk=self.cfg.chunk, renderer=self.source if source else None,
                                with_normals=False)
