"""Section 4.4: patch-wise backprop at fixed samples equals full backprop."""

from __future__ import annotations

import pytest
import torch
from render_helpers import (check_retained_graph_matches_the_patches, front_view, retained_graph_ray_losses,
    tiny_renderer)

from nerfart_plugin.objectives.losses import weight_regularization
from nerfart_plugin.rendering.two_pass import (backprop_patches, backprop_retained, render_fixed_samples,
    render_with_graph)


def _renderer(backbone: str, occupancy: int) -> torch.nn.Module:
    return tiny_renderer(backbone, occupancy)


def _view(H: int = 12, W: int = 10) -> dict:
    return front_view(H, W, 12.0)


def _image_loss(rgb: torch.Tensor) -> torch.Tensor:
    # a non-trivial function of the whole image (couples all pixels, like CLIP/VGG do)
    img = rgb.reshape(12, 10, 3)
    target = torch.linspace(0, 1, 3, dtype=rgb.dtype)
    return ((img.mean((0, 1)) - target) ** 2).sum() + (img[1:] - img[:-1]).abs().mean()


@pytest.mark.parametrize("backbone", ["nerf", "volsdf", "neus"])
@pytest.mark.parametrize("occupancy", [0, 8])
def test_patch_backprop_equals_full_backprop(backbone: str, occupancy: int) -> None:
    torch.manual_seed(0)
    r = _renderer(backbone, occupancy)
    if r.occupancy is not None:
        r.occupancy.update(r.field, 0, force=True)
    view = _view()
    lam_reg = 0.1
    g = torch.Generator().manual_seed(3)
    first = render_fixed_samples(r, view, chunk=37, perturb=True, generator=g)

    # full backprop at the same samples
    r.zero_grad()
    full = r(view, perturb=False, t_samples=first["t_samples"])
    torch.testing.assert_close(full["rgb"].detach(), first["rgb"], rtol=1e-6, atol=1e-6)
    loss = _image_loss(full["rgb"]) + lam_reg * weight_regularization(full["weights"], full["t"])
    loss.backward()
    ref = {n: p.grad.clone() for n, p in r.named_parameters() if p.grad is not None}
    assert ref, "no parameter received a gradient"

    # two-pass: image gradient, then patches
    r.zero_grad()
    img = first["rgb"].clone().requires_grad_(True)
    rgb_grad = torch.autograd.grad(_image_loss(img), img)[0]
    backprop_patches(r, view, first["t_samples"], rgb_grad, patch_rays=29,
                     ray_losses={"reg": (lam_reg, lambda o, _: weight_regularization(o["weights"], o["t"]))})
    worst = 0.0
    for n, p in r.named_parameters():
        if n in ref:
            denom = ref[n].abs().max().clamp_min(1e-12)
            worst = max(worst, float((p.grad - ref[n]).abs().max() / denom))
    assert worst <= 1e-4, f"max relative gradient difference {worst:.2e}"


def test_same_t_samples_reproduce_the_render() -> None:
    r = _renderer("nerf", 0)
    view = _view()
    a = r(view, perturb=True, generator=torch.Generator().manual_seed(1))
    b = r(view, perturb=False, t_samples=a["t_samples"])
    c = r(view, perturb=True, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(a["rgb"], b["rgb"])
    assert not torch.allclose(a["t_samples"], c["t_samples"]), "jitter should differ between seeds"


@pytest.mark.parametrize("backbone", ["volsdf", "neus"])
def test_patch_backprop_under_a_mixed_precision_autocast_backpropagates_outside_it(backbone: str) -> None:
    """trainer.precision=bf16-mixed: Lightning runs the stylization step under autocast. The patches are
    rendered under it (the colour net in bfloat16), but their backward runs outside it, as PyTorch's AMP
    recipe does: the float32 geometry net's backward matmuls stay float32, the parameter gradients are
    those of a forward under autocast followed by a plain backward, bit for bit."""
    torch.manual_seed(0)
    r = _renderer(backbone, 8)
    r.occupancy.update(r.field, 0, force=True)
    view = _view()
    first = render_fixed_samples(r, view, chunk=64, perturb=True, generator=torch.Generator().manual_seed(3))
    rgb_grad = torch.randn(first["rgb"].shape, generator=torch.Generator().manual_seed(4))
    n = first["rgb"].shape[0]

    r.zero_grad()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = r(view, perturb=False, t_samples=first["t_samples"])
        surrogate = (out["rgb"] * rgb_grad).sum()
    surrogate.backward()  # the recipe: backward outside the autocast
    ref = {k: p.grad.clone() for k, p in r.named_parameters() if p.grad is not None}

    seen: list[bool] = []

    def backward(loss: torch.Tensor) -> None:
        seen.append(torch.is_autocast_enabled("cpu"))
        loss.backward()

    r.zero_grad()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        backprop_patches(r, view, first["t_samples"], rgb_grad, patch_rays=n, backward=backward)
    assert seen == [False]
    geometry = [k for k in ref if k.startswith("field.geo_net")]
    assert geometry and all(r.get_parameter(k).grad.dtype == torch.float32 for k in ref)
    for k, g in ref.items():
        torch.testing.assert_close(r.get_parameter(k).grad, g, rtol=0, atol=0, msg=k)


def _ray_losses() -> dict:
    """Eq. 7 and the field's regularizers (eikonal for the SDF fields), as the stylization passes them."""
    return retained_graph_ray_losses()


@pytest.mark.parametrize("backbone", ["nerf", "volsdf", "neus"])
@pytest.mark.parametrize("occupancy", [0, 8])
def test_retained_graph_backprop_equals_patch_backprop(backbone: str, occupancy: int) -> None:
    """stylize.backprop=retain: one render with grad (marched, early termination) and a backward through
    its kept graph give pass 1's image, samples and ray losses, and the patch backprop's gradient."""
    check_retained_graph_matches_the_patches(backbone, occupancy, torch.device("cpu"))


def test_retained_graph_survives_a_view_that_misses_the_grid() -> None:
    """Every ray misses the occupancy grid: the kept graph still reaches the parameters (one probe sample,
    as the patch re-render), so the optimizer step has something to act on and the backward does not fail."""
    r = tiny_renderer("volsdf", 8, 16)
    r.occupancy.update(r.field, 0, force=True)
    view = front_view(6, 5, 12.0)
    view = {**view, "rays_o": view["rays_o"] + torch.tensor([10.0, 0.0, 0.0])}  # shifted far off the box
    kept, chunks = render_with_graph(r, view, chunk=16, perturb=False)
    assert float(kept["opacity"].abs().max()) == 0.0
    backprop_retained(chunks, view, torch.ones(30, 3), _ray_losses())


def test_retained_chunks_must_match_the_batch() -> None:
    r = tiny_renderer("nerf", 0, 8)
    view = _view()
    _, chunks = render_with_graph(r, view, chunk=50, perturb=False)
    with pytest.raises(ValueError, match="pass the batch they rendered"):
        backprop_retained(chunks[:1], view, torch.ones(120, 3))


def test_retained_backward_runs_outside_the_autocast() -> None:
    r = tiny_renderer("volsdf", 8, 16, beta_init=0.003)
    r.occupancy.update(r.field, 0, force=True)
    view = _view()
    seen: list[bool] = []

    def backward(loss: torch.Tensor) -> None:
        seen.append(torch.is_autocast_enabled("cpu"))
        loss.backward()

    with torch.autocast("cpu", dtype=torch.bfloat16):
        _, chunks = render_with_graph(r, view, chunk=64, perturb=True, generator=torch.Generator().manual_seed(1))
        backprop_retained(chunks, view, torch.ones(120, 3), backward=backward)
    assert seen == [False]
    assert all(p.grad is None or p.grad.dtype == torch.float32 for p in r.parameters())
