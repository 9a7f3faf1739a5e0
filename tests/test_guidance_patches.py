"""Random local patches (Eq. 6)."""

from __future__ import annotations

import torch

from nerfart_plugin.guidance import random_patches


def test_random_patches_shapes_content_and_grad() -> None:
    img = torch.arange(2 * 3 * 40 * 60, dtype=torch.float32).reshape(2, 3, 40, 60) / 1e4
    img.requires_grad_()
    gen = torch.Generator().manual_seed(0)
    crops, boxes = random_patches(img, num=5, size_frac=0.25, out_size=10, generator=gen, return_boxes=True)
    assert crops.shape == (5, 3, 10, 10) and boxes.shape == (5, 5)
    side = boxes[:, 3] - boxes[:, 1]
    assert torch.all(side == 10) and torch.all(boxes[:, 3] <= 60) and torch.all(boxes[:, 4] <= 40)
    # same side as output -> exact crop
    b, x0, y0 = (int(v) for v in boxes[0, :3])
    assert torch.allclose(crops[0], img[b, :, y0 : y0 + 10, x0 : x0 + 10], atol=1e-5)
    crops.sum().backward()
    assert img.grad.abs().sum() > 0
    again = random_patches(img.detach(), 5, 0.25, 10, torch.Generator().manual_seed(0))
    assert torch.allclose(again, crops.detach())


def test_random_patches_upsample_default_fraction() -> None:
    img = torch.rand(1, 3, 100, 80)
    out = random_patches(img, num=3, out_size=32)  # side = 8 px (1/10 of 80)
    assert out.shape == (3, 3, 32, 32) and torch.isfinite(out).all()
