"""Random local patches (Eq. 6): area reading of the paper's 1/10, patches on the subject."""

from __future__ import annotations

import pytest
import torch

from nerfart_plugin.guidance import random_patches
from nerfart_plugin.guidance.patches import patch_side, subject_box


def test_random_patches_shapes_content_and_grad() -> None:
    img = torch.arange(2 * 3 * 40 * 60, dtype=torch.float32).reshape(2, 3, 40, 60) / 1e4
    img.requires_grad_()
    gen = torch.Generator().manual_seed(0)
    # area 100 of 2400 px -> 10 px side
    crops, boxes = random_patches(img, num=5, area_frac=100 / 2400, out_size=10, generator=gen, return_boxes=True)
    assert crops.shape == (5, 3, 10, 10) and boxes.shape == (5, 5)
    side = boxes[:, 3] - boxes[:, 1]
    assert torch.all(side == 10) and torch.all(boxes[:, 3] <= 60) and torch.all(boxes[:, 4] <= 40)
    assert torch.all(boxes[:, 1:3] >= 0)
    # same side as output -> exact crop
    b, x0, y0 = (int(v) for v in boxes[0, :3])
    assert torch.allclose(crops[0], img[b, :, y0 : y0 + 10, x0 : x0 + 10], atol=1e-5)
    crops.sum().backward()
    assert img.grad.abs().sum() > 0
    again = random_patches(img.detach(), 5, 100 / 2400, 10, torch.Generator().manual_seed(0))
    assert torch.allclose(again, crops.detach())


def test_patch_side_is_the_area_reading() -> None:
    # the official release: 112 px patches on a 270x480 canvas = 0.097 of its area
    assert patch_side(270, 480, 0.097) == 112
    assert patch_side(128, 128, 0.1) == 40  # not 13 px (the side reading)
    assert patch_side(72, 128, 0.1) == 30
    assert patch_side(10, 10, 1.0) == 10 and patch_side(4, 400, 0.9) == 4  # never larger than the view
    with pytest.raises(ValueError):
        patch_side(10, 10, 0.0)


def test_patches_land_on_the_subject() -> None:
    opacity = torch.zeros(128, 128)
    opacity[40:90, 70:110] = 1.0  # the subject: rows 40-89, columns 70-109
    box = subject_box(opacity)
    assert box == (70, 40, 110, 90)
    assert subject_box(torch.zeros(8, 8)) is None
    img = torch.rand(1, 3, 128, 128)
    _, boxes = random_patches(img, 200, 0.1, 16, torch.Generator().manual_seed(1), return_boxes=True, region=box)
    cx, cy = (boxes[:, 1] + boxes[:, 3]) / 2, (boxes[:, 2] + boxes[:, 4]) / 2
    assert torch.all((cx >= 70 - 1) & (cx <= 110 + 1) & (cy >= 40 - 1) & (cy <= 90 + 1))
    # without a region the centres spread over the whole view
    _, free = random_patches(img, 200, 0.1, 16, torch.Generator().manual_seed(1), return_boxes=True)
    assert float(((free[:, 1] + free[:, 3]) / 2).min()) < 40


def test_random_patches_upsample_default_fraction() -> None:
    img = torch.rand(1, 3, 100, 80)
    out = random_patches(img, num=3, out_size=32)  # side = round(sqrt(0.1 * 8000)) = 28 px
    assert out.shape == (3, 3, 32, 32) and torch.isfinite(out).all()
