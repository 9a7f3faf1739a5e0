"""A tiny renderer and one camera view, shared by the two-pass and the CUDA tests."""

from __future__ import annotations

import torch

from nerfart_plugin.data.rays import camera_batch
from nerfart_plugin.data.setup import SceneSetup
from nerfart_plugin.systems.base import build_renderer


def tiny_renderer(backbone: str, occupancy: int, samples: int = 12, **backbone_kw: object) -> torch.nn.Module:
    """``backbone`` on a 16-cell grid (NeuS: a 4-frequency MLP) in an object setup; ``occupancy``: grid cells
    per side (0: no occupancy grid); ``samples`` per ray; ``backbone_kw``: backbone settings."""
    setup = SceneSetup("object", 1.0, False, [1.0, 1.0, 1.0], False, occupancy, samples, True)
    enc = {"name": "grid", "resolution": 16} if backbone != "neus" else {"name": "frequency", "n_freqs": 4}
    return build_renderer({"backbone": {"name": backbone, **backbone_kw}, "encoding": enc,
                           "render": {"occupancy": {"warmup_steps": 0}}}, setup)


def front_view(H: int, W: int, focal: float) -> dict:
    """The ray batch of a pinhole camera 2.5 units in front of the origin, looking at it."""
    K = torch.tensor([[focal, 0, W / 2], [0, focal, H / 2], [0, 0, 1]])
    c2w = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -2.5]])
    return camera_batch(K, c2w, H, W, 1.0, 4.0, ndc=False)


def check_sharp_surface_under_autocast(backbone: str, device: torch.device, dtype: torch.dtype) -> None:
    """Mixed precision on a trained scene: with the surface a few thousandths of the box wide (VolSDF beta
    0.002, NeuS inv_s ~1100) and a 64^3 occupancy grid, the render under ``dtype`` autocast stays within
    40 dB of float32's and the finite-difference SDF gradient (eikonal, normals) within 0.02. A bfloat16
    cell index (exact only to 256) read the wrong occupancy cells (a trained selfie rendered 11.7 dB from
    float32) and a bfloat16 geometry net made the gradient's difference quotient noise."""
    from nerfart_plugin.objectives.losses import psnr
    from nerfart_plugin.utils.device import to_device

    torch.manual_seed(0)
    sharp = {"beta_init": 0.002} if backbone == "volsdf" else {"init_variance": 0.7}
    r = tiny_renderer(backbone, occupancy=64, samples=48, **sharp).to(device)
    r.occupancy.update(r.field, 0, force=True)
    view = to_device(front_view(24, 20, 24.0), device)
    x = torch.nn.functional.normalize(torch.randn(512, 3, device=device), dim=-1) * r.field.radius  # on the sphere
    d = torch.nn.functional.normalize(torch.randn(512, 3, device=device), dim=-1)
    with torch.no_grad():
        ref, ref_grad = r.render_chunked(view, chunk=128)["rgb"], r.field._forward_fd(x, d)["gradient"]
        with torch.autocast(device.type, dtype=dtype):
            low, low_grad = r.render_chunked(view, chunk=128)["rgb"], r.field._forward_fd(x, d)["gradient"]
    assert float(psnr(low.float(), ref)) >= 40.0
    torch.testing.assert_close(low_grad.float(), ref_grad, atol=0.02, rtol=0.0)


#: fields made opaque at init (a sharp sphere, a dense fog), so rays stop early and a march has work to skip
OPAQUE = {
    "nerf": {"density_bias": 4.0},
    "volsdf": {"beta_init": 0.003},
    "neus": {"init_variance": 0.8, "alpha_mode": "sections"},
}


def retained_graph_ray_losses() -> dict:
    """Eq. 7 and the field's regularizers (eikonal for the SDF fields), as the stylization passes them."""
    from nerfart_plugin.objectives.losses import weight_regularization

    return {"reg": (0.1, lambda o, _: weight_regularization(o["weights"], o["t"])),
            "eikonal": (0.1, lambda o, _: o["regularizers"].get("eikonal", o["rgb"].sum() * 0))}


def check_retained_graph_matches_the_patches(backbone: str, occupancy: int, device: torch.device) -> None:
    """``stylize.backprop=retain`` on ``device``: one marched render with grad and a backward through its kept
    graph give the no-grad march's image, samples and opacity, the patch backprop's ray-loss values and its
    parameter gradient (1e-4 relative), on an opaque field whose rays stop early."""
    import pytest

    from nerfart_plugin.rendering.two_pass import (backprop_patches, backprop_retained, render_fixed_samples,
        render_with_graph)
    from nerfart_plugin.utils.device import to_device

    torch.manual_seed(0)
    r = tiny_renderer(backbone, occupancy, 32, **OPAQUE[backbone]).to(device)
    if r.occupancy is not None:
        r.occupancy.update(r.field, 0, force=True)
    view = to_device(front_view(20, 16, 20.0), device)
    n = view["rays_o"].shape[0]
    rgb_grad = torch.randn(n, 3, generator=torch.Generator().manual_seed(4)).to(device)

    def grads() -> dict[str, torch.Tensor]:
        out = {k: p.grad.clone() for k, p in r.named_parameters() if p.grad is not None}
        r.zero_grad()
        return out

    r.zero_grad()
    first = render_fixed_samples(r, view, chunk=97, perturb=True, generator=torch.Generator(device).manual_seed(2))
    patch_terms = backprop_patches(r, view, first["t_samples"], rgb_grad, 97, retained_graph_ray_losses())
    ref = grads()
    kept, chunks = render_with_graph(r, view, chunk=97, perturb=True, generator=torch.Generator(device).manual_seed(2))
    assert all(not v.requires_grad for v in kept.values())
    torch.testing.assert_close(kept["t_samples"], first["t_samples"], rtol=0, atol=0)
    torch.testing.assert_close(kept["rgb"], first["rgb"], rtol=0, atol=1e-6)
    torch.testing.assert_close(kept["opacity"], first["opacity"], rtol=0, atol=1e-6)
    assert sum(int(c["samples_evaluated"]) for c in chunks) < 0.8 * n * 32, "opaque rays should stop early"
    retained_terms = backprop_retained(chunks, view, rgb_grad, retained_graph_ray_losses())
    got = grads()
    assert ref and set(got) == set(ref)
    for k, g in ref.items():
        rel = float((got[k] - g).norm() / g.norm().clamp_min(1e-12))
        assert rel <= 1e-4, f"{k}: relative gradient difference {rel:.1e}"
    assert set(retained_terms) == set(patch_terms)
    for k, v in patch_terms.items():
        assert retained_terms[k] == pytest.approx(v, rel=1e-4, abs=1e-7), k
