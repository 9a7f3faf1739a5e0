"""Random local patches for the local CLIP losses (Eq. 6)."""

from __future__ import annotations

import torch
from torch import Tensor
from torchvision.ops import roi_align


def random_patches(
    img: Tensor,
    num: int,
    size_frac: float = 0.1,
    out_size: int = 224,
    generator: torch.Generator | None = None,
    return_boxes: bool = False,
) -> Tensor | tuple[Tensor, Tensor]:
    """Crop ``num`` random square patches and resample them to ``out_size``.

    Patch side = ``round(size_frac * min(H, W))`` pixels (at least 2; paper: a
    local patch side of 1/10 of the image side), top-left corner uniform over
    valid positions, source image uniform over the batch. Resampling uses
    torchvision's ``roi_align`` (bilinear, ``aligned=True``, adaptive sampling
    so downscaling averages instead of aliasing); differentiable w.r.t. ``img``
    and without copying the image per patch.

    Args:
        img: ``[B,3,H,W]`` images.
        num: number of patches.
        size_frac: patch side as a fraction of the shorter image side, in (0, 1].
        out_size: output side (e.g. the guidance's ``input_size``).
        generator: CPU ``torch.Generator`` for reproducible draws.
        return_boxes: also return ``[num,5]`` boxes ``(b, x0, y0, x1, y1)`` in pixels.
    Returns: ``[num,3,out_size,out_size]`` (and the boxes).
    """
    if img.dim() != 4:
        raise ValueError(f"random_patches expects [B,C,H,W], got {tuple(img.shape)}")
    if not 0.0 < size_frac <= 1.0:
        raise ValueError(f"size_frac must be in (0, 1], got {size_frac}")
    B, _, H, W = img.shape
    side = max(2, min(H, W, int(round(size_frac * min(H, W)))))
    b = torch.randint(0, B, (num,), generator=generator)
    x0 = torch.randint(0, W - side + 1, (num,), generator=generator)
    y0 = torch.randint(0, H - side + 1, (num,), generator=generator)
    boxes = torch.stack([b, x0, y0, x0 + side, y0 + side], dim=1).to(img.dtype)
    crops = roi_align(
        img,
        boxes.to(img.device),
        output_size=(out_size, out_size),
        spatial_scale=1.0,
        sampling_ratio=-1,
        aligned=True,
    )
    return (crops, boxes) if return_boxes else crops
