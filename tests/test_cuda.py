"""The CUDA path: device placement, mixed precision, two-pass exactness on the GPU, a tiny pipeline on
device=cuda. Every test here is skipped without a CUDA device (the CPU suite never depends on one);
``benchmarks/gpu_check.sh`` runs them where a GPU is at hand."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from pipeline_helpers import tiny_cfg
from render_helpers import (check_retained_graph_matches_the_patches, check_sharp_surface_under_autocast, front_view,
    tiny_renderer)

from nerfart_plugin.rendering.two_pass import backprop_patches, render_fixed_samples
from nerfart_plugin.utils.device import to_device

pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")]


def _renderer(backbone: str, occupancy: int = 8) -> torch.nn.Module:
    return tiny_renderer(backbone, occupancy)


def _view() -> dict:
    return front_view(24, 20, 24.0)


def _loss(rgb: torch.Tensor) -> torch.Tensor:
    img = rgb.reshape(24, 20, 3)
    return ((img.mean((0, 1)) - torch.linspace(0, 1, 3, device=rgb.device)) ** 2).sum() + (img[1:] - img[:-1]).abs().mean()


@pytest.mark.parametrize("backbone", ["nerf", "volsdf", "neus"])
def test_everything_lives_on_the_gpu_and_matches_the_cpu(backbone: str) -> None:
    """Every parameter and buffer (occupancy grid included) moves with .to('cuda'); the render is the CPU's."""
    torch.manual_seed(0)
    cpu = _renderer(backbone)
    if cpu.occupancy is not None:
        cpu.occupancy.update(cpu.field, 0, force=True)
    gpu = _renderer(backbone)
    gpu.load_state_dict(cpu.state_dict())
    gpu = gpu.to("cuda")
    assert all(t.is_cuda for t in [*gpu.parameters(), *gpu.buffers()])
    view = _view()
    with torch.no_grad():
        a = cpu.render_chunked(view, chunk=128, with_normals=False)
        b = gpu.render_chunked(to_device(view, torch.device("cuda")), chunk=128, with_normals=False)
    assert b["rgb"].is_cuda
    torch.testing.assert_close(b["rgb"].cpu(), a["rgb"], atol=2e-4, rtol=1e-4)


@pytest.mark.parametrize("backbone", ["nerf", "volsdf", "neus"])
def test_two_pass_backprop_is_exact_on_cuda(backbone: str) -> None:
    torch.manual_seed(0)
    r = _renderer(backbone).to("cuda")
    if r.occupancy is not None:
        r.occupancy.update(r.field, 0, force=True)
    view = to_device(_view(), torch.device("cuda"))
    first = render_fixed_samples(r, view, chunk=97, perturb=True, generator=torch.Generator(device="cuda").manual_seed(3))
    r.zero_grad()
    _loss(r(view, perturb=False, t_samples=first["t_samples"])["rgb"]).backward()
    ref = {n: p.grad.clone() for n, p in r.named_parameters() if p.grad is not None}
    r.zero_grad()
    img = first["rgb"].clone().requires_grad_(True)
    backprop_patches(r, view, first["t_samples"], torch.autograd.grad(_loss(img), img)[0], patch_rays=61)
    worst = max(float((p.grad - ref[n]).abs().max() / ref[n].abs().max().clamp_min(1e-12))
                for n, p in r.named_parameters() if n in ref)
    assert worst <= 1e-4, f"max relative gradient difference {worst:.2e}"


@pytest.mark.parametrize("backbone", ["nerf", "volsdf", "neus"])
def test_retained_graph_backprop_matches_the_patches_on_cuda(backbone: str) -> None:
    """stylize.backprop=retain on the GPU: the patch backprop's gradient through the kept graph."""
    check_retained_graph_matches_the_patches(backbone, 8, torch.device("cuda"))


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_autocast_renders_finite_and_close(dtype: torch.dtype) -> None:
    """Mixed precision (trainer.precision=16-mixed / bf16-mixed): a render and its gradient stay finite and
    the image stays within a few percent of float32's."""
    torch.manual_seed(0)
    r = _renderer("volsdf").to("cuda")
    r.occupancy.update(r.field, 0, force=True)
    view = to_device(_view(), torch.device("cuda"))
    ref = r(view)["rgb"].detach()
    with torch.autocast("cuda", dtype=dtype):
        out = r(view)
        loss = _loss(out["rgb"].float())
    loss.backward()
    assert torch.isfinite(out["rgb"]).all() and all(torch.isfinite(p.grad).all() for p in r.parameters()
                                                    if p.grad is not None)
    assert float((out["rgb"].float() - ref).abs().mean()) < 0.02


@pytest.mark.parametrize("backbone", ["volsdf", "neus"])
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_autocast_keeps_a_sharp_surface_on_cuda(backbone: str, dtype: torch.dtype) -> None:
    """trainer.precision=16-mixed / bf16-mixed on a trained-sharp surface (render_helpers)."""
    check_sharp_surface_under_autocast(backbone, torch.device("cuda"), dtype)


@pytest.mark.slow
@pytest.mark.parametrize("precision", ["32-true", "bf16-mixed"])
def test_tiny_pipeline_on_cuda(tmp_path: Path, precision: str) -> None:
    """Reconstruct and stylize the shipped head on device=cuda: checkpoints load back on the CPU."""
    from nerfart_plugin.api import open_run
    from nerfart_plugin.data.datamodule import DEFAULT_SCENE
    from nerfart_plugin.run.pipeline import run

    res = run(tiny_cfg(tmp_path, DEFAULT_SCENE, "device=cuda", f"trainer.precision={precision}", "guidance=toy",
                       "prompt=red", "reconstruct.steps=30", "stylize.steps=3"))
    for stage in ("reconstruction", "stylization"):
        back = open_run(res[stage]["dir"], device="cpu")
        assert next(back.renderer.parameters()).device.type == "cpu"
        assert back.render(0)["rgb"].std() > 1


def test_clip_guidance_on_cuda_matches_the_cpu() -> None:
    """CLIP's image tower on CUDA (fp16 under ``auto``, its weights cast once, the patch embedding a matmul)
    gives the CPU float32 embeddings and image gradients within fp16's precision; moved back to the CPU it
    casts its weights anew there."""
    from nerfart_plugin.guidance import build_guidance
    from nerfart_plugin.guidance.clip import TINY_TEST_OVERRIDES

    cfg = {"name": "clip", "allow_random_weights": True,
           "pretrained": None, "model_overrides": TINY_TEST_OVERRIDES, "precision": "fp32"}
    torch.manual_seed(0)
    ref = build_guidance(cfg)
    g = build_guidance({**cfg, "precision": "auto"})
    g.net.load_state_dict(ref.net.state_dict())
    g.to("cuda")
    cos = torch.nn.functional.cosine_similarity
    x = torch.rand(3, 3, 40, 48, requires_grad=True)
    e_ref = ref.encode_image(x)
    g_ref = torch.autograd.grad(e_ref.square().sum(), x)[0]
    xc = x.detach().cuda().requires_grad_(True)
    e = g.encode_image(xc)
    grad = torch.autograd.grad(e.square().sum(), xc)[0]
    assert g.compute_dtype(xc.device) == torch.float16 and e.dtype == torch.float32
    assert cos(e.cpu(), e_ref).min() > 0.999 and cos(grad.cpu().flatten(1), g_ref.flatten(1)).min() > 0.99
    g.to("cpu")
    assert cos(g.encode_image(x), e_ref).min() > 0.999
