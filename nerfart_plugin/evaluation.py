"""Stylization metrics: CLIP score, CLIP directional similarity, view consistency.

* CLIP score: mean cosine between the image embedding of each rendered view and
  the target text embedding.
* CLIP directional similarity: mean cosine between the image direction
  E(I_sty) − E(I_src) and the text direction E(t_tgt) − E(t_src) (what Eq. 4
  optimizes; 1 is perfect agreement).
* View consistency: each frame of a smooth camera path is warped into its
  neighbour with the rendered depth and the colours compared (mean absolute
  error in [0,1] units over pixels visible in both, with an occlusion test on
  the neighbour's depth). Lower is more consistent; report it next to the
  source field's own figure, which is the floor set by sampling and shading.
"""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F


@torch.no_grad()
def clip_scores(guidance, stylized: torch.Tensor, source: torch.Tensor, prompt: str,
                source_prompt: str) -> dict[str, float]:
    """``stylized``/``source`` [B,3,H,W] in [0,1] renders of the same views."""
    e_sty = F.normalize(guidance.encode_image(stylized).float(), dim=-1)
    e_src = F.normalize(guidance.encode_image(source).float(), dim=-1)
    t = F.normalize(guidance.encode_text([prompt, source_prompt]).float(), dim=-1)
    img_dir = F.normalize(e_sty - e_src, dim=-1, eps=1e-8)
    txt_dir = F.normalize(t[0] - t[1], dim=-1, eps=1e-8)
    return {
        "clip_score": float((e_sty @ t[0]).mean()),
        "clip_score_source": float((e_src @ t[0]).mean()),
        "clip_directional_similarity": float((img_dir @ txt_dir).mean()),
    }


def warp_error(rgb_i: torch.Tensor, depth_i: torch.Tensor, opacity_i: torch.Tensor, K_i: torch.Tensor,
               c2w_i: torch.Tensor, rgb_j: torch.Tensor, depth_j: torch.Tensor, K_j: torch.Tensor,
               c2w_j: torch.Tensor, rel_depth_tol: float = 0.03) -> Optional[float]:
    """Mean |rgb_i − warp(rgb_j)| over pixels of view i visible in view j.

    Args: ``rgb_*`` [H,W,3]; ``depth_*`` [H,W] distance along unit rays (not NDC);
    ``opacity_i`` [H,W]; ``K_*`` [3,3]; ``c2w_*`` [3,4] OpenCV. Returns None if no
    pixel is visible in both views.
    """
    H, W = depth_i.shape
    dev = rgb_i.device
    v, u = torch.meshgrid(torch.arange(H, device=dev) + 0.5, torch.arange(W, device=dev) + 0.5, indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], -1).reshape(-1, 3)
    d_cam = pix @ torch.linalg.inv(K_i).T
    d_cam = d_cam / d_cam.norm(dim=-1, keepdim=True)
    d_world = d_cam @ c2w_i[:, :3].T
    X = c2w_i[:, 3] + d_world * depth_i.reshape(-1, 1)
    Xc = (X - c2w_j[:, 3]) @ c2w_j[:, :3]  # world -> camera j (R^T (X - c))
    z = Xc[:, 2]
    uvw = Xc @ K_j.T
    uv = uvw[:, :2] / uvw[:, 2:].clamp_min(1e-8)
    grid = torch.stack([uv[:, 0] / W * 2 - 1, uv[:, 1] / H * 2 - 1], -1).reshape(1, H, W, 2)
    sample = lambda img: F.grid_sample(img.permute(2, 0, 1)[None].float(), grid, align_corners=False,
                                       mode="bilinear", padding_mode="border")[0].permute(1, 2, 0)
    rgb_w = sample(rgb_j)
    depth_w = sample(depth_j[..., None])[..., 0].reshape(-1)
    dist_j = Xc.norm(dim=-1)
    inside = (z > 1e-6) & (grid.reshape(-1, 2).abs() <= 1).all(-1)
    visible = (depth_w - dist_j).abs() <= rel_depth_tol * dist_j
    valid = inside & visible & (opacity_i.reshape(-1) > 0.5)
    if not valid.any():
        return None
    return float((rgb_i.reshape(-1, 3)[valid] - rgb_w.reshape(-1, 3)[valid]).abs().mean())


def view_consistency(frames: list[dict[str, torch.Tensor]], K: torch.Tensor, c2ws: torch.Tensor) -> Optional[float]:
    """Mean :func:`warp_error` between consecutive frames (dicts with rgb, depth, opacity [H,W,·])."""
    errs = []
    for a in range(len(frames) - 1):
        fa, fb = frames[a], frames[a + 1]
        e = warp_error(fa["rgb"], fa["depth"][..., 0], fa["opacity"][..., 0], K, c2ws[a].to(K),
                       fb["rgb"], fb["depth"][..., 0], K, c2ws[a + 1].to(K))
        if e is not None:
            errs.append(e)
    return float(sum(errs) / len(errs)) if errs else None
