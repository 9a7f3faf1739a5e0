"""3D Gaussian splats and a differentiable rasterizer for them: gsplat's on CUDA where it is installed, this
module's own vectorized PyTorch one everywhere else (CPU included).

A splat set (:class:`Splats`) holds N Gaussians: means [N,3], unit quaternions [N,4] (w, x, y, z), log scales
[N,3], opacity logits [N] and colours as the degree-0 spherical-harmonic coefficient [N,3] (``rgb = 0.5 + C0 ·
f_dc``), the layout of the 3DGS ``.ply`` (:mod:`nerfart_plugin.export.splats`).

The PyTorch rasterizer follows 3DGS (Kerbl et al. 2023): each Gaussian is projected with the EWA Jacobian (its
2D covariance dilated by 0.3 px², as the reference does), the image is cut into ``tile`` x ``tile`` pixel tiles,
each tile composites, front to back, the ``max_per_tile`` nearest Gaussians whose 3-sigma box overlaps it
(``alpha = min(0.99, opacity · exp(-½ dᵀ Σ⁻¹ d))``, alphas below 1/255 dropped), and the rest of the ray shows the
background. All of it is batched over tiles, so autograd gives the gradients of means, shapes, opacities and
colours. Pixel ``(u, v)`` is sampled at its centre ``(u + 0.5, v + 0.5)`` (OpenCV intrinsics), as the fields' rays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor

#: the degree-0 spherical harmonic, Y_0^0: rgb = 0.5 + C0 * f_dc
C0 = 0.28209479177387814
#: the smallest alpha a Gaussian contributes (3DGS: 1/255) and the largest (0.99)
MIN_ALPHA, MAX_ALPHA = 1.0 / 255.0, 0.99
#: added to each projected covariance (px²): the screen-space low-pass of 3DGS
DILATION = 0.3


@dataclass
class Splats:
    """N Gaussians (tensors; trainable when they require grad).

    Attributes:
        means: [N,3] centres; quats: [N,4] rotations (w, x, y, z; normalized when used); log_scales: [N,3];
        opacities: [N] logits; colours: [N,3] degree-0 SH coefficients (``rgb = 0.5 + C0 · colours``).
    """

    means: Tensor
    quats: Tensor
    log_scales: Tensor
    opacities: Tensor
    colours: Tensor

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def parameters(self) -> list[Tensor]:
        return [self.means, self.quats, self.log_scales, self.opacities, self.colours]

    def detach(self) -> "Splats":
        return Splats(*(t.detach().clone() for t in self.parameters()))

    def to(self, device: torch.device | str) -> "Splats":
        return Splats(*(t.to(device) for t in self.parameters()))

    def rgb(self) -> Tensor:
        """[N,3] colours in [0, 1]."""
        return (0.5 + C0 * self.colours).clamp(0.0, 1.0)


def quat_to_rotmat(q: Tensor) -> Tensor:
    """[N,4] quaternions (w, x, y, z; any length) -> [N,3,3] rotation matrices."""
    w, x, y, z = F.normalize(q, dim=-1).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(-1, 3, 3)


def rotmat_to_quat(R: Tensor) -> Tensor:
    """[N,3,3] rotation matrices -> [N,4] unit quaternions (w, x, y, z), w >= 0."""
    m = R
    t = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cands = torch.stack([
        torch.stack([1 + t, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], -1),
        torch.stack([m[:, 2, 1] - m[:, 1, 2], 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], m[:, 0, 1] + m[:, 1, 0],
                     m[:, 0, 2] + m[:, 2, 0]], -1),
        torch.stack([m[:, 0, 2] - m[:, 2, 0], m[:, 0, 1] + m[:, 1, 0], 1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
                     m[:, 1, 2] + m[:, 2, 1]], -1),
        torch.stack([m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1],
                     1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], -1),
    ], 1)  # [N,4 candidates,4]
    best = torch.stack([1 + t, 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], 1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
                        1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], -1).argmax(-1)
    q = F.normalize(cands[torch.arange(len(m)), best], dim=-1)
    return torch.where(q[:, :1] < 0, -q, q)


@dataclass
class Projected:
    """Gaussians projected into one camera: ``xy`` [N,2] pixel centres, ``conic`` [N,3] (a, b, c of the inverse
    2D covariance), ``radius`` [N] (pixels, 3 sigma), ``depth`` [N], ``visible`` [N] bool."""

    xy: Tensor
    conic: Tensor
    radius: Tensor
    depth: Tensor
    visible: Tensor


def project(splats: Splats, c2w: Tensor, K: Tensor, H: int, W: int, near: float = 0.01) -> Projected:
    """EWA projection of ``splats`` into the camera ``c2w`` [3,4] (OpenCV) with intrinsics ``K`` [3,3] at H x W."""
    R_wc = c2w[:3, :3].T
    t = -R_wc @ c2w[:3, 3]
    p = splats.means @ R_wc.T + t  # camera frame
    z = p[:, 2]
    zc = z.clamp_min(near)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    xy = torch.stack([fx * p[:, 0] / zc + cx, fy * p[:, 1] / zc + cy], -1)
    Rg = quat_to_rotmat(splats.quats)
    S = torch.exp(splats.log_scales)
    M = Rg * S[:, None, :]  # R diag(s)
    cov = M @ M.transpose(1, 2)
    cov_c = R_wc @ cov @ R_wc.T
    # the projection's Jacobian, its x/z and y/z clamped to 1.3x the field of view as 3DGS does
    lim_x, lim_y = 1.3 * 0.5 * W / fx, 1.3 * 0.5 * H / fy
    tx = (p[:, 0] / zc).clamp(-lim_x, lim_x) * zc
    ty = (p[:, 1] / zc).clamp(-lim_y, lim_y) * zc
    zeros = torch.zeros_like(zc)
    J = torch.stack([torch.stack([fx / zc, zeros, -fx * tx / zc**2], -1),
                     torch.stack([zeros, fy / zc, -fy * ty / zc**2], -1)], 1)  # [N,2,3]
    cov2 = J @ cov_c @ J.transpose(1, 2)
    a = cov2[:, 0, 0] + DILATION
    b = cov2[:, 0, 1]
    c = cov2[:, 1, 1] + DILATION
    det = (a * c - b * b).clamp_min(1e-12)
    conic = torch.stack([c / det, -b / det, a / det], -1)
    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt((mid * mid - det).clamp_min(0.1))
    radius = 3.0 * torch.sqrt(lam)
    visible = (z > near) & (xy[:, 0] + radius > 0) & (xy[:, 0] - radius < W) & (xy[:, 1] + radius > 0) \
        & (xy[:, 1] - radius < H)
    return Projected(xy, conic, radius, z, visible)


def rasterize(splats: Splats, c2w: Tensor, K: Tensor, H: int, W: int, background: Optional[Tensor] = None,
              tile: int = 8, max_per_tile: int = 256) -> dict[str, Tensor]:
    """Render ``splats`` from one camera (see the module docstring): ``rgb`` [H,W,3] and ``alpha`` [H,W]
    (the share of each pixel the splats cover); differentiable in the splats' tensors. ``background``: [3]
    colour behind them (default white)."""
    out = rasterize_tiles(splats, c2w, K, H, W, None, background, tile, max_per_tile)
    ty, tx = math.ceil(H / tile), math.ceil(W / tile)
    img = out["rgb"].reshape(ty, tx, tile, tile, 3).permute(0, 2, 1, 3, 4).reshape(ty * tile, tx * tile, 3)[:H, :W]
    cov = out["alpha"].reshape(ty, tx, tile, tile).permute(0, 2, 1, 3).reshape(ty * tile, tx * tile)[:H, :W]
    return {"rgb": img, "alpha": cov}


def tile_pixels(H: int, W: int, tile: int = 8) -> Tensor:
    """[T, tile*tile] the flat pixel index (row * W + column) of each pixel of each tile, -1 beyond the image:
    what :func:`rasterize_tiles`' outputs are laid out as."""
    ty, tx = math.ceil(H / tile), math.ceil(W / tile)
    v = torch.arange(ty * tile).reshape(ty, 1, tile, 1).expand(ty, tx, tile, tile)
    u = torch.arange(tx * tile).reshape(1, tx, 1, tile).expand(ty, tx, tile, tile)
    flat = torch.where((v < H) & (u < W), v * W + u, torch.full_like(v, -1))
    return flat.reshape(ty * tx, tile * tile)


def rasterize_tiles(splats: Splats, c2w: Tensor, K: Tensor, H: int, W: int, tiles: Optional[Tensor] = None,
                    background: Optional[Tensor] = None, tile: int = 8, max_per_tile: int = 256) -> dict[str, Tensor]:
    """The tiles ``tiles`` [T'] (default: every tile, row-major) of :func:`rasterize`'s image: ``rgb`` [T',P,3] and
    ``alpha`` [T',P] (P = tile², pixels row-major in the tile; :func:`tile_pixels` maps them to the image). A fit
    renders a random share of the tiles each step."""
    device = splats.means.device
    background = torch.ones(3, device=device) if background is None else background.to(device)
    ty, tx = math.ceil(H / tile), math.ceil(W / tile)
    tiles = torch.arange(ty * tx, device=device) if tiles is None else tiles.to(device)
    proj = project(splats, c2w.to(device).float(), K.to(device).float(), H, W)
    order = torch.argsort(proj.depth.detach())
    keep = order[proj.visible[order]]
    P = tile * tile
    if keep.numel() == 0:
        return {"rgb": background.expand(len(tiles), P, 3).clone(), "alpha": torch.zeros(len(tiles), P, device=device)}
    xy, conic, radius = proj.xy[keep], proj.conic[keep], proj.radius[keep].detach()
    opac, rgb = torch.sigmoid(splats.opacities[keep]), splats.rgb()[keep]
    # each tile's Gaussians: those whose 3-sigma box overlaps it, nearest first, at most max_per_tile
    x0 = (tiles % tx) * tile
    y0 = (tiles // tx) * tile
    gx, gy = xy[:, 0].detach(), xy[:, 1].detach()
    over = ((gx[None] + radius[None] > x0[:, None]) & (gx[None] - radius[None] < x0[:, None] + tile)
            & (gy[None] + radius[None] > y0[:, None]) & (gy[None] - radius[None] < y0[:, None] + tile))  # [T',N]
    rank = over.cumsum(-1)
    k = max(1, int(min(max_per_tile, int(rank[:, -1].max()))))
    slot = torch.where(over & (rank <= k), rank - 1, torch.full_like(rank, k))
    n = xy.shape[0]
    idx = torch.full((len(tiles), k + 1), n, dtype=torch.long, device=device)
    idx.scatter_(1, slot, torch.arange(n, device=device).expand(len(tiles), n))
    idx = idx[:, :k]  # [T',k]: n marks an empty slot (an opacity-0 Gaussian)
    pad = lambda t: torch.cat([t, t.new_zeros((1, *t.shape[1:]))])  # noqa: E731
    g_xy, g_conic, g_opac, g_rgb = pad(xy)[idx], pad(conic)[idx], pad(opac)[idx], pad(rgb)[idx]
    py, px = torch.meshgrid(torch.arange(tile, device=device), torch.arange(tile, device=device), indexing="ij")
    cx = (x0[:, None] + px.reshape(1, -1)).float() + 0.5  # [T',P]
    cy = (y0[:, None] + py.reshape(1, -1)).float() + 0.5
    dx = cx[:, :, None] - g_xy[:, None, :, 0]  # [T',P,k]
    dy = cy[:, :, None] - g_xy[:, None, :, 1]
    a, b, c = (g_conic[:, None, :, i] for i in range(3))
    power = (-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy).clamp(max=0.0)
    alpha = (g_opac[:, None, :] * torch.exp(power)).clamp(max=MAX_ALPHA)
    alpha = alpha * (alpha >= MIN_ALPHA)
    log_t = torch.log1p(-alpha)
    trans = torch.exp(torch.cumsum(log_t, -1) - log_t)  # exclusive: the light left in front of each Gaussian
    w = alpha * trans
    cover = w.sum(-1)
    colour = torch.einsum("tpk,tkc->tpc", w, g_rgb) + (1.0 - cover)[..., None] * background
    return {"rgb": colour, "alpha": cover}


def gsplat_available(device: torch.device) -> bool:
    """True when gsplat (CUDA) can rasterize on ``device``."""
    if device.type != "cuda":
        return False
    try:
        import gsplat  # noqa: F401  (optional: CUDA only)
    except ImportError:
        return False
    return True


def rasterize_gsplat(splats: Splats, c2w: Tensor, K: Tensor, H: int, W: int,
                     background: Optional[Tensor] = None) -> dict[str, Tensor]:
    """:func:`rasterize` by gsplat's CUDA kernels (the same model; gsplat's own tiling and no cap per tile)."""
    from gsplat import rasterization  # optional: CUDA only

    device = splats.means.device
    background = torch.ones(3, device=device) if background is None else background.to(device)
    w2c = torch.eye(4, device=device)
    w2c[:3, :3] = c2w[:3, :3].T.to(device)
    w2c[:3, 3] = -(c2w[:3, :3].T @ c2w[:3, 3]).to(device)
    colours, alphas, _ = rasterization(splats.means, F.normalize(splats.quats, dim=-1), torch.exp(splats.log_scales),
                                       torch.sigmoid(splats.opacities), splats.rgb(), w2c[None], K.to(device)[None],
                                       W, H, backgrounds=background[None], eps2d=DILATION)
    return {"rgb": colours[0], "alpha": alphas[0, ..., 0]}
