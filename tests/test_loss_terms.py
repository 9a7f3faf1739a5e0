"""One declaration per loss term: the tables, lambda_* weights (0 skips a term), and field regularizers
consumed generically, so encoding.tv_weight reaches both stages' losses."""

from __future__ import annotations

import torch

from nerfart_plugin.data.rays import camera_batch
from nerfart_plugin.data.setup import SceneSetup
from nerfart_plugin.guidance import ToyGuidance
from nerfart_plugin.guidance.style import Style
from nerfart_plugin.guidance.vgg import EdgePerceptual
from nerfart_plugin.systems.base import build_renderer, step_seed
from nerfart_plugin.systems.reconstruction import RECONSTRUCTION_LOSSES, ReconstructionSystem
from nerfart_plugin.systems.stylization import StylizationSystem
from nerfart_plugin.systems.stylization_losses import (STYLE_IMAGE_LOSSES, STYLIZATION_IMAGE_LOSSES,
                                                       STYLIZATION_RAY_LOSSES)

BACKBONE = {"name": "volsdf", "hidden_dim": 16, "n_layers": 1, "feature_dim": 8, "color_hidden_dim": 16,
            "color_layers": 1}
RENDER = {"num_samples": 8, "occupancy": {"resolution": 8}}


def _setup(masks: bool = True, occupancy: int = 8) -> SceneSetup:
    return SceneSetup("object", 1.0, False, [1.0, 1.0, 1.0], False, occupancy, 8, masks)


def _rays(n: int = 64) -> dict:
    g = torch.Generator().manual_seed(0)
    o = torch.tensor([0.0, 0.0, -2.5]).expand(n, 3).contiguous()
    d = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0]) + 0.2 * torch.randn(n, 3, generator=g), dim=-1)
    return {"rays_o": o, "rays_d": d, "near": torch.full((n,), 1.0), "far": torch.full((n,), 4.0),
            "rgb": torch.rand(n, 3, generator=g), "mask": (torch.rand(n, generator=g) > 0.5).float()}


def _recon(tv_weight: float, rays: dict | None = None, **cfg) -> ReconstructionSystem:
    enc = {"name": "grid", "resolution": 8, "n_components": 2, "out_features": 8, "tv_weight": tv_weight}
    return ReconstructionSystem({"reconstruct": {"batch_rays": 32, **cfg}, "backbone": BACKBONE, "encoding": enc, "render": RENDER}, _setup(),
                                train_rays=rays if rays is not None else _rays())


def test_every_term_is_one_row_with_its_lambda():
    from nerfart_plugin.config.schema import ExperimentConfig, ReconstructConfig, StyleImageConfig

    for table, section in ((RECONSTRUCTION_LOSSES, ReconstructConfig),
                           (STYLIZATION_IMAGE_LOSSES + STYLIZATION_RAY_LOSSES, ExperimentConfig),
                           (STYLE_IMAGE_LOSSES, StyleImageConfig)):
        names = [t.name for t in table]
        assert len(names) == len(set(names))
        assert all(t.lambda_key in section.model_fields and t.doc for t in table)


def test_tv_weight_reaches_the_reconstruction_loss():
    torch.manual_seed(0)
    system = _recon(tv_weight=0.5)
    assert system.field.regularizer_names == ("eikonal", "grid_tv")
    assert system.reg_lambdas == {"eikonal": 0.1, "grid_tv": 1.0}  # lambda_eikonal; the encoding weighs grid_tv
    batch = system.sample_batch(0)
    out = system.renderer(batch, perturb=True)
    terms, weights = system.losses(out, batch)
    assert set(terms) == {"rgb", "mask", "eikonal", "grid_tv"}
    # the planes get the TV gradient: the term is part of the loss, not just computed
    tv = terms["grid_tv"]
    planes = list(system.field.encoding.planes.parameters())
    assert torch.autograd.grad(weights["grid_tv"] * tv, planes, retain_graph=True)[0].abs().sum() > 0
    assert float(tv.detach()) == float(system.field.encoding.regularizers()["grid_tv"].detach())
    off = _recon(tv_weight=0.0)
    terms, _ = off.losses(off.renderer(batch, perturb=True), batch)
    assert "grid_tv" not in terms and off.field.regularizer_names == ("eikonal",)


def test_lambda_zero_and_missing_masks_skip_terms():
    system = _recon(tv_weight=0.0, lambda_eikonal=0.0, lambda_mask=0.0)
    batch = system.sample_batch(0)
    terms, _ = system.losses(system.renderer(batch, perturb=True), batch)
    assert set(terms) == {"rgb"}
    enc = {"name": "grid", "resolution": 8, "n_components": 2}
    no_masks = ReconstructionSystem({"reconstruct": {}, "backbone": BACKBONE, "encoding": enc, "render": RENDER}, _setup(masks=False), train_rays=_rays())
    assert no_masks.lambdas["mask"] == 0.0
    nerf = ReconstructionSystem({"reconstruct": {}, "backbone": {"name": "nerf", "hidden_dim": 16}, "encoding": enc, "render": RENDER}, _setup(), train_rays=_rays())
    assert nerf.reg_lambdas == {}  # a density field has no eikonal term


def test_mask_ray_share_draws_the_subject_more_often():
    """reconstruct.mask_ray_share of each batch comes from inside the mattes once
    reconstruct.mask_ray_share_after steps have passed (before: the plain uniform draw, as with 0);
    each step's batch depends on (seed, step) only; scenes without mattes ignore the setting."""
    rays = _rays(4000)
    inside = rays["mask"].mean()  # ~0.5
    share = _recon(0.0, rays, mask_ray_share=0.8, mask_ray_share_after=3, batch_rays=2000)
    batch = share.sample_batch(3)
    assert batch["mask"].mean() > 0.8 + 0.15 * inside  # 80% from inside plus the uniform part's share
    assert torch.equal(batch["rays_d"], share.sample_batch(3)["rays_d"])
    g = torch.Generator().manual_seed(step_seed(0, 2))  # the plain uniform draw of earlier releases
    plain = rays["rays_d"][torch.randint(0, 4000, (2000,), generator=g)]
    assert torch.equal(share.sample_batch(2)["rays_d"], plain)  # step 2 < mask_ray_share_after: uniform
    uniform = _recon(0.0, rays, mask_ray_share=0.0, mask_ray_share_after=0, batch_rays=2000)
    assert torch.equal(uniform.sample_batch(2)["rays_d"], plain)
    assert abs(float(uniform.sample_batch(3)["mask"].mean()) - float(uniform.train_rays["mask"].mean())) < 0.1
    enc = {"name": "grid", "resolution": 8, "n_components": 2}
    unmasked = {k: v for k, v in _rays().items() if k != "mask"}
    no_masks = ReconstructionSystem({"reconstruct": {"mask_ray_share": 0.9, "batch_rays": 32}, "backbone": BACKBONE, "encoding": enc, "render": RENDER},
                                    _setup(masks=False), train_rays=unmasked)
    assert no_masks.foreground_rays() is None and no_masks.sample_batch(0)["rays_o"].shape == (32, 3)


def test_auto_mask_ray_share_is_the_scene_setups_decision():
    """reconstruct.mask_ray_share=auto (the default) draws the share the scene setup decided from the
    mattes; without a decision (no mattes, or an older setup) the draw is uniform."""
    from dataclasses import replace

    rays = _rays(4000)
    enc = {"name": "grid", "resolution": 8, "n_components": 2}
    cfg = {"batch_rays": 2000, "mask_ray_share_after": 0}
    decided = ReconstructionSystem({"reconstruct": cfg, "backbone": BACKBONE, "encoding": enc, "render": RENDER}, replace(_setup(), mask_ray_share=0.8), train_rays=rays)
    assert decided.cfg.mask_ray_share == "auto" and decided.mask_ray_share == 0.8
    assert decided.sample_batch(3)["mask"].mean() > 0.8 + 0.15 * rays["mask"].mean()
    undecided = ReconstructionSystem({"reconstruct": cfg, "backbone": BACKBONE, "encoding": enc, "render": RENDER}, _setup(), train_rays=rays)
    assert undecided.mask_ray_share == 0.0 and undecided.foreground_rays() is None
    g = torch.Generator().manual_seed(step_seed(0, 3))
    assert torch.equal(undecided.sample_batch(3)["rays_d"], rays["rays_d"][torch.randint(0, 4000, (2000,), generator=g)])
    number = ReconstructionSystem({"reconstruct": {**cfg, "mask_ray_share": 0.3}, "backbone": BACKBONE, "encoding": enc, "render": RENDER},
                                  replace(_setup(), mask_ray_share=0.8), train_rays=rays)
    assert number.mask_ray_share == 0.3  # a number in the config wins over the setup's decision


def _stylization(cfg: dict, tv_weight: float = 0.5, occupancy: int = 8) -> StylizationSystem:
    enc = {"name": "grid", "resolution": 8, "n_components": 2, "tv_weight": tv_weight}
    torch.manual_seed(0)
    setup = _setup(occupancy=occupancy)
    src = build_renderer({"backbone": BACKBONE, "encoding": enc, "render": RENDER}, setup)
    views = [camera_batch(torch.tensor([[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]]), torch.eye(4)[:3], 8, 8, 0.5, 3.5, False)]
    style = Style(ToyGuidance(), EdgePerceptual(), False, "", "red", "red", "a photo", negatives=("auto", ["blue"]))
    return StylizationSystem({"stylize": {"steps": 2, **cfg}, "experiment": {"lambda_global": 0.0, "lambda_local": 0.0},
                              "backbone": BACKBONE, "encoding": enc, "render": RENDER}, setup, style,
                             src.state_dict(), views)


def test_stylize_num_samples_only_where_an_occupancy_grid_places_them():
    """stylize.num_samples replaces the reconstruction's samples per ray only where an occupancy grid puts them
    at the surface; a scene without a grid (NDC) stylizes and renders its views at render.num_samples."""
    guided, uniform = _stylization({"num_samples": 4}), _stylization({"num_samples": 4}, occupancy=0)
    assert (guided.renderer.num_samples, guided.source.num_samples, guided.renderer.view_samples) == (4, 4, 4)
    assert (uniform.renderer.num_samples, uniform.source.num_samples, uniform.renderer.view_samples) == (8, 8, None)


def test_tv_weight_reaches_the_stylization_ray_terms_unless_geometry_is_frozen():
    s = _stylization({})
    ray = s.ray_losses()
    assert {k: w for k, (w, _) in ray.items()} == {"reg": 0.1, "silhouette": 0.0, "eikonal": 0.1, "grid_tv": 1.0}
    frozen = _stylization({"freeze_geometry": True})
    assert {k: w for k, (w, _) in frozen.ray_losses().items()} == {"reg": 0.1, "silhouette": 0.0, "eikonal": 0.0,
                                                                   "grid_tv": 0.0}
    assert _stylization({"local_patches": 0}).lambdas["local"] == 0.0


def test_learning_rates_decay_to_lr_final():
    """Both rates decay exponentially from their initial value to reconstruct.lr_final of it at
    reconstruct.steps, and stay there."""
    system = _recon(0.0, lr_final=0.05, steps=10)
    sched = system.configure_optimizers()["lr_scheduler"]["scheduler"]
    factor = sched.lr_lambdas[0]
    assert factor(0) == 1.0 and abs(factor(5) - 0.05**0.5) < 1e-9 and abs(factor(10) - 0.05) < 1e-9
    assert factor(20) == factor(10)
