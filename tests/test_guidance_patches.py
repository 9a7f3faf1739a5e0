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


@pytest.mark.parametrize("side_px, out_size", [(9, 32), (28, 28), (81, 224)])
def test_upsampled_patches_take_roi_aligns_samples_and_gradient(side_px: int, out_size: int) -> None:
    """The grid_sample path (side <= out_size) is roi_align(aligned=True): values and image gradient,
    on two source images, with boxes touching every border of the image."""
    from torchvision.ops import roi_align

    from nerfart_plugin.guidance.patches import upsample_boxes

    H, W = 90, 120
    img = torch.rand(2, 3, H, W, generator=torch.Generator().manual_seed(3), requires_grad=True)
    corners = [(0, 0), (W - side_px, 0), (0, H - side_px), (W - side_px, H - side_px),
               ((W - side_px) // 3, (H - side_px) // 2)]
    boxes = torch.tensor([[b, x, y, x + side_px, y + side_px] for b in (0, 1) for x, y in corners], dtype=torch.float32)
    ours = upsample_boxes(img, boxes, side_px, out_size)
    ref = roi_align(img, boxes, output_size=(out_size, out_size), spatial_scale=1.0, sampling_ratio=-1, aligned=True)
    assert ours.shape == ref.shape == (len(boxes), 3, out_size, out_size)
    assert torch.allclose(ours, ref, atol=5e-5)  # float32 rounding of the sample coordinates
    up = torch.randn_like(ref)
    g_ours = torch.autograd.grad((ours * up).sum(), img)[0]
    g_ref = torch.autograd.grad((ref * up).sum(), img)[0]
    assert float((g_ours - g_ref).norm()) < 1e-4 * float(g_ref.norm())  # measured: 1e-5 (coordinate rounding)
    assert float(g_ours[1].abs().sum()) > 0 and float(g_ours[0].abs().sum()) > 0  # both images receive gradient


def test_downscaled_patches_average_instead_of_aliasing() -> None:
    """side > out_size keeps roi_align's adaptive sampling: a 1-pixel checkerboard averages to grey."""
    from nerfart_plugin.guidance.patches import upsample_boxes

    yy, xx = torch.meshgrid(torch.arange(64), torch.arange(64), indexing="ij")
    img = ((yy + xx) % 2).float().expand(1, 3, 64, 64).contiguous()
    crops = random_patches(img, num=4, area_frac=0.5, out_size=8, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(crops, torch.full_like(crops, 0.5), atol=0.05)
    with pytest.raises(ValueError, match="roi_align"):
        upsample_boxes(img, torch.zeros(1, 5), side=45, out_size=8)
