"""Geometry can move while stylizing: the occupancy grid follows the stylized field (issue: the
reconstruction's band used to confine the surface to a one-cell shell, leaving holes)."""

from __future__ import annotations

import torch

from nerfart_plugin.data.rays import camera_batch
from nerfart_plugin.data.setup import SceneSetup
from nerfart_plugin.guidance import ToyGuidance
from nerfart_plugin.guidance.style import Style
from nerfart_plugin.guidance.vgg import EdgePerceptual
from nerfart_plugin.systems.base import build_renderer
from nerfart_plugin.systems.stylization import StylizationSystem

BACKBONE = {"name": "volsdf", "hidden_dim": 32, "n_layers": 2, "feature_dim": 16, "radius": 0.3,
            "color_hidden_dim": 32, "color_layers": 1, "color_normal": False, "beta_init": 0.01}
ENCODING = {"name": "grid", "resolution": 16, "n_components": 4}
RENDER = {"num_samples": 32, "occupancy": {"resolution": 32, "threshold": 0.01, "update_every": 16}}


def setup() -> SceneSetup:
    return SceneSetup(capture="object", bound=1.0, background_model=False, background_color=[1.0, 1.0, 1.0],
                      ndc=False, occupancy_resolution=32, num_samples=32, has_masks=True)


def ring_rays(radius: float, n: int = 64) -> dict:
    """Rays along -z passing the centre at distance ``radius`` (tangent-ish to a sphere of that size)."""
    a = torch.linspace(0, 2 * torch.pi, n + 1)[:-1]
    o = torch.stack([radius * a.cos(), radius * a.sin(), torch.full_like(a, 2.0)], -1)
    d = torch.tensor([0.0, 0.0, -1.0]).expand(n, 3)
    return {"rays_o": o, "rays_d": d.clone(), "near": torch.full((n,), 0.5), "far": torch.full((n,), 3.5)}


def system_for(cfg: dict) -> StylizationSystem:
    torch.manual_seed(0)
    src = build_renderer({"backbone": BACKBONE, "encoding": ENCODING, "render": RENDER}, setup())
    src.occupancy.update(src.field, 0, force=True)  # the reconstruction's grid: a shell around r = 0.3
    views = [camera_batch(torch.tensor([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]]), torch.eye(4)[:3], 16, 16,
                          0.5, 3.5, False)]
    style = Style(ToyGuidance(), EdgePerceptual(), False, "", "red", "red", "a photo", negatives=("auto", ["blue"]))
    return StylizationSystem({"stylize": {"steps": 10, **cfg}, "experiment": {"lambda_global": 0.0, "lambda_local": 0.0},
                              "backbone": BACKBONE, "encoding": ENCODING, "render": RENDER}, setup(), style,
                             src.state_dict(), views)


def grow_surface(system: StylizationSystem, by: float) -> None:
    """Move the stylized surface outward by ``by`` (world units): sdf -> sdf - by."""
    with torch.no_grad():
        system.field.geo_net.out.bias[0] -= by


def test_surface_moved_beyond_the_band_renders_without_holes() -> None:
    followed = system_for({"occupancy_update_every": 8})
    frozen_grid = system_for({"occupancy_update_every": 0})
    rays = ring_rays(0.5)  # misses the source sphere (r = 0.3), hits the grown one (r = 0.6)
    with torch.no_grad():
        assert float(followed.renderer.render_chunked(rays)["opacity"].mean()) < 0.05
    for s in (followed, frozen_grid):
        grow_surface(s, 0.3)  # far outside the source's band (one cell diagonal = 0.11)
        s.follow_geometry(0)
    with torch.no_grad():
        hit = followed.renderer.render_chunked(rays)["opacity"]
        hole = frozen_grid.renderer.render_chunked(rays)["opacity"]
    assert float(hit.min()) > 0.95, "the moved surface must be sampled everywhere"
    assert float(hole.mean()) < 0.1, "without following, the reconstruction's grid skips the new surface"
    # the source renderer (I_src of Eq. 4/9) keeps the reconstruction's grid and geometry
    with torch.no_grad():
        assert float(followed.source.render_chunked(rays)["opacity"].max()) < 0.05
    assert followed.renderer.occupancy.sdf_band >= 3 * followed.renderer.occupancy.cell_size


def test_frozen_geometry_keeps_the_grid() -> None:
    s = system_for({"occupancy_update_every": 8, "freeze_geometry": True})
    before = s.renderer.occupancy.occupied.clone()
    assert not s.follow_geometry(0)
    assert torch.equal(before, s.renderer.occupancy.occupied)


def test_a_bf16_mixed_stylization_step_backpropagates_outside_the_trainers_autocast() -> None:
    """Lightning runs training_step, and so the step's dL/dI and its patch backward, under
    trainer.precision's autocast. Both backward passes run with the autocast off (PyTorch's AMP recipe):
    inside it, the float32 geometry net's and the contrastive logits' backward matmuls ran in bfloat16."""
    from nerfart_plugin.run.fit import train_steps

    s = system_for({"occupancy_update_every": 0, "chunk": 64, "patch_size": 8})
    seen: dict[str, list[bool]] = {"image terms": [], "geometry net": []}

    def record(part: str):
        return lambda grad: seen[part].append(torch.is_autocast_enabled("cpu"))

    image_losses = s.image_losses

    def hooked_image_losses(*args):
        terms = image_losses(*args)
        for t in terms.values():
            t.register_hook(record("image terms"))
        return terms

    s.image_losses = hooked_image_losses

    def hook_geometry(module, inputs, out) -> None:
        if out.requires_grad:
            out.register_hook(record("geometry net"))

    s.field.geo_net.register_forward_hook(hook_geometry)
    train_steps(s, 2, torch.device("cpu"), {"precision": "bf16-mixed"})
    assert len(seen["image terms"]) >= 2 and len(seen["geometry net"]) >= 2 * 4, seen  # 2 steps, 4 patches each
    assert not any(seen["image terms"]) and not any(seen["geometry net"]), seen


def test_retained_graph_stylization_step_matches_the_patch_backprop(monkeypatch) -> None:
    """stylize.backprop=retain through the real Trainer: the first step's parameter gradients (read before
    the optimizer step) are the paper's patch backprop's, to float rounding."""
    import lightning as L

    import nerfart_plugin.systems.stylization as stylization
    from nerfart_plugin.run.fit import train_steps

    calls: list[str] = []
    for name in ("render_with_graph", "backprop_patches"):
        real = getattr(stylization, name)
        monkeypatch.setattr(stylization, name, lambda *a, _f=real, _n=name, **k: calls.append(_n) or _f(*a, **k))

    class FirstGradients(L.Callback):
        def __init__(self) -> None:
            self.grads: dict[str, torch.Tensor] = {}

        def on_before_optimizer_step(self, trainer, module, optimizer) -> None:
            if not self.grads:
                self.grads = {n: p.grad.clone() for n, p in module.renderer.named_parameters() if p.grad is not None}

    cfg = {"occupancy_update_every": 0, "chunk": 64, "patch_size": 8}
    patch, retain = FirstGradients(), FirstGradients()
    train_steps(system_for(cfg), 1, torch.device("cpu"), callbacks=[patch])
    assert calls == ["backprop_patches"]
    kept = system_for({**cfg, "backprop": "retain"})
    train_steps(kept, 1, torch.device("cpu"), callbacks=[retain])
    assert calls == ["backprop_patches", "render_with_graph"]
    assert patch.grads and set(retain.grads) == set(patch.grads)
    assert any(k.startswith("field.geo_net") for k in patch.grads), "the geometry should receive gradient"
    for k, g in patch.grads.items():
        rel = float((retain.grads[k] - g).norm() / g.norm().clamp_min(1e-12))
        assert rel <= 1e-4, f"{k}: relative gradient difference {rel:.1e}"
    assert set(kept.timings) >= {"render_nograd", "patch_backprop"}


def test_retained_graph_refuses_views_too_large_to_keep(monkeypatch) -> None:
    import pytest

    import nerfart_plugin.systems.stylization as stylization
    from nerfart_plugin.errors import ConfigError

    monkeypatch.setattr(stylization, "MAX_GRAD_SAMPLES", 16 * 16 * 16 - 1)  # 16x16 rays x stylize.num_samples, less 1
    with pytest.raises(ConfigError, match="stylize.backprop=patch"):
        system_for({"backprop": "retain"})
    system_for({"backprop": "patch"})  # the paper's patches are bounded by stylize.patch_size
