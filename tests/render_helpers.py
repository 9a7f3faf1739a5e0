"""A tiny renderer and one camera view, shared by the two-pass and the CUDA tests."""

from __future__ import annotations

import torch

from nerfart_plugin.data.rays import camera_batch
from nerfart_plugin.systems.base import build_renderer
from nerfart_plugin.systems.scene_setup import SceneSetup


def tiny_renderer(backbone: str, occupancy: int, samples: int = 12, **backbone_kw: object) -> torch.nn.Module:
    """``backbone`` on a 16-cell grid (NeuS: a 4-frequency MLP) in an object setup; ``occupancy``: grid cells
    per side (0: no occupancy grid); ``samples`` per ray; ``backbone_kw``: backbone settings."""
    setup = SceneSetup("object", 1.0, False, [1.0, 1.0, 1.0], False, occupancy, samples, True)
    enc = {"name": "grid", "resolution": 16} if backbone != "neus" else {"name": "frequency", "n_freqs": 4}
    return build_renderer({"name": backbone, **backbone_kw}, enc, {"occupancy": {"warmup_steps": 0}}, setup)


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
    from nerfart_plugin.losses import psnr
    from nerfart_plugin.systems.base import to_device

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
