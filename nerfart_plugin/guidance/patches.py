"""Random local patches for the local contrastive loss (Eq. 6)."""

from __future__ import annotations

import math
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor
from torchvision.ops import roi_align


def patch_side(H: int, W: int, area_frac: float) -> int:
    """Side (pixels) of a square patch covering ``area_frac`` of an H x W view, at most min(H, W).

    The paper's "1/10 of the input" is an AREA: the official code crops 112 px
    patches from a 270x480 canvas (0.097 of it). At 128x128 this gives 40 px.
    """
    if not 0.0 < area_frac <= 1.0:
        raise ValueError(f"area_frac must be in (0, 1], got {area_frac}")
    return max(2, min(H, W, int(round(math.sqrt(area_frac * H * W)))))


def subject_box(opacity: Tensor, threshold: float = 0.5) -> Optional[tuple[int, int, int, int]]:
    """Bounding box ``(x0, y0, x1, y1)`` (pixels, exclusive ends) of ``opacity`` [H,W] > threshold, or None."""
    ys, xs = torch.nonzero(opacity > threshold, as_tuple=True)
    if ys.numel() == 0:
        return None
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def random_patches(
    img: Tensor,
    num: int,
    area_frac: float = 0.1,
    out_size: int = 224,
    generator: torch.Generator | None = None,
    return_boxes: bool = False,
    region: Optional[tuple[int, int, int, int]] = None,
) -> Tensor | tuple[Tensor, Tensor]:
    """Crop ``num`` random square patches and resample them to ``out_size``.

    Patch side = :func:`patch_side` (``area_frac`` of the view's area). Patch
    centres are uniform over ``region`` (``(x0, y0, x1, y1)`` pixels, e.g.
    :func:`subject_box` of the source render's opacity, so patches land on the
    subject, not on empty background; default: the whole view), then the patch
    is shifted to lie inside the image. Source image uniform over the batch.
    Resampling is torchvision's ``roi_align`` (bilinear, ``aligned=True``,
    adaptive sampling so downscaling averages instead of aliasing); when a
    patch is upsampled (side <= ``out_size``, every patch at the paper's
    resolutions) ``roi_align`` takes one bilinear sample per output pixel, and
    :func:`upsample_boxes` takes the same samples with ``grid_sample``, whose
    backward is several times cheaper on CPU. Differentiable w.r.t. ``img``
    and without copying the image per patch.

    Args:
        img: ``[B,3,H,W]`` images.
        num: number of patches.
        area_frac: patch area as a fraction of the view's area, in (0, 1].
        out_size: output side (e.g. the guidance's ``input_size``).
        generator: CPU ``torch.Generator`` for reproducible draws.
        return_boxes: also return ``[num,5]`` boxes ``(b, x0, y0, x1, y1)`` in pixels.
        region: where patch centres may fall.
    Returns: ``[num,3,out_size,out_size]`` (and the boxes).
    """
    if img.dim() != 4:
        raise ValueError(f"random_patches expects [B,C,H,W], got {tuple(img.shape)}")
    B, _, H, W = img.shape
    side = patch_side(H, W, area_frac)
    rx0, ry0, rx1, ry1 = region if region is not None else (0, 0, W, H)
    rx0, ry0 = max(0, min(rx0, W - 1)), max(0, min(ry0, H - 1))
    rx1, ry1 = max(rx0 + 1, min(rx1, W)), max(ry0 + 1, min(ry1, H))
    b = torch.randint(0, B, (num,), generator=generator)
    cx = rx0 + torch.rand(num, generator=generator) * (rx1 - rx0)
    cy = ry0 + torch.rand(num, generator=generator) * (ry1 - ry0)
    x0 = (cx - side / 2).round().long().clamp(0, W - side)
    y0 = (cy - side / 2).round().long().clamp(0, H - side)
    boxes = torch.stack([b, x0, y0, x0 + side, y0 + side], dim=1).to(img.dtype)
    if side <= out_size:
        crops = upsample_boxes(img, boxes.to(img.device), side, out_size)
    else:
        crops = roi_align(img, boxes.to(img.device), output_size=(out_size, out_size), spatial_scale=1.0,
                          sampling_ratio=-1, aligned=True)
    return (crops, boxes) if return_boxes else crops


def upsample_boxes(img: Tensor, boxes: Tensor, side: int, out_size: int) -> Tensor:
    """Bilinear resampling of square boxes to ``out_size`` pixels, as ``roi_align(aligned=True)`` when
    ``side <= out_size`` (one sample per output pixel, at its centre), through ``grid_sample``.

    Output pixel ``i`` of a box starting at pixel ``x0`` samples ``x0 + (i + 0.5) side / out_size - 0.5``
    (pixel centres at integers), clamped to the image as ``roi_align`` clamps. The batch is stacked
    along the rows, so one ``grid_sample`` call serves every source image without a copy per box.

    Args:
        img: ``[B,C,H,W]`` images.
        boxes: ``[N,5]`` rows ``(b, x0, y0, x0 + side, y0 + side)`` in pixels.
        side: the boxes' side (pixels), at most ``out_size``.
        out_size: output side (pixels).
    Returns: ``[N,C,out_size,out_size]``.
    """
    if side > out_size:
        raise ValueError(f"upsample_boxes resamples boxes up, not down: side {side} > out_size {out_size}; "
                         "use roi_align with adaptive sampling to average when downscaling")
    B, C, H, W = img.shape
    n = boxes.shape[0]
    offsets = (torch.arange(out_size, device=img.device, dtype=img.dtype) + 0.5) * (side / out_size) - 0.5
    xs = (boxes[:, 1:2] + offsets).clamp(0, W - 1)  # [N,out] pixel columns
    ys = (boxes[:, 2:3] + offsets).clamp(0, H - 1) + boxes[:, 0:1] * H  # [N,out] rows of the stacked batch
    gx = (xs + 0.5) * (2.0 / W) - 1.0  # align_corners=False: pixel centres at (p + 0.5) / size
    gy = (ys + 0.5) * (2.0 / (B * H)) - 1.0
    grid = torch.stack([gx[:, None, :].expand(n, out_size, out_size),
                        gy[:, :, None].expand(n, out_size, out_size)], dim=-1)
    stacked = img.transpose(0, 1).reshape(1, C, B * H, W)  # a view when B == 1
    out = F.grid_sample(stacked, grid.reshape(1, n * out_size, out_size, 2), mode="bilinear",
                        padding_mode="border", align_corners=False)
    return out.reshape(C, n, out_size, out_size).transpose(0, 1).contiguous()
