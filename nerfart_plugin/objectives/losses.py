"""NeRF-Art losses (Eq. 2-9) as pure functions on tensors.

No model lives here: callers encode images/text with a
:class:`nerfart_plugin.guidance.base.Guidance` and pass the embeddings in.
Every function that takes embeddings L2-normalizes them itself, so raw encoder
outputs can be passed directly.

Shapes: image embeddings ``[B, D]``, a text embedding ``[D]`` (``[1, D]`` is
accepted too), negatives ``[M, D]``. Every loss returns a 0-dim tensor.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from nerfart_plugin.errors import ConfigError

log = logging.getLogger(__name__)

#: Epsilon of the direction normalization in :func:`directional_clip_loss`.
#: A direction ``v`` is mapped to ``v / max(||v||, DIRECTION_EPS)``. Embeddings
#: are unit vectors, so direction norms lie in [0, 2]; real stylization moves
#: them by >= 1e-2 within a few steps, so 1e-4 only affects the degenerate
#: start (stylized == source) and float noise around it.
DIRECTION_EPS = 1e-4


def _unit(x: Tensor, eps: float = 1e-8) -> Tensor:
    """L2-normalize along the last dim (``x / max(||x||, eps)``; zero stays zero)."""
    return F.normalize(x, dim=-1, eps=eps)


def _as_row(x: Tensor, name: str) -> Tensor:
    """``[D]`` or ``[1, D]`` -> ``[1, D]``; anything else is a shape error."""
    if x.dim() == 1:
        return x.unsqueeze(0)
    if x.dim() == 2 and x.shape[0] == 1:
        return x
    raise ValueError(f"{name} must be a single embedding of shape [D] or [1, D], got {tuple(x.shape)}")


def _check_2d(x: Tensor, name: str) -> None:
    if x.dim() != 2:
        raise ValueError(f"{name} must have shape [B, D], got {tuple(x.shape)}")


def absolute_clip_loss(img_emb: Tensor, txt_emb: Tensor) -> Tensor:
    """Eq. 3: mean over B of ``1 - cos(E_i(I_tgt), E_t(t_tgt))``.

    Args:
        img_emb: ``[B, D]`` image embeddings of the stylized renders.
        txt_emb: ``[D]`` (or ``[B, D]``) target text embedding.
    Returns: 0-dim tensor in [0, 2].
    """
    _check_2d(img_emb, "img_emb")
    txt = txt_emb if txt_emb.dim() == 2 and txt_emb.shape[0] == img_emb.shape[0] else _as_row(txt_emb, "txt_emb")
    cos = (_unit(img_emb) * _unit(txt)).sum(-1)
    return (1.0 - cos).mean()


def directional_clip_loss(
    img_emb: Tensor,
    src_img_emb: Tensor,
    tgt_txt_emb: Tensor,
    src_txt_emb: Tensor,
    eps: float = DIRECTION_EPS,
) -> Tensor:
    """Eq. 4: mean over B of ``1 - cos(E_i(I_tgt) - E_i(I_src), E_t(t_tgt) - E_t(t_src))``.

    Embeddings are L2-normalized first (as in StyleGAN-NADA / NeRF-Art), then
    the two directions are normalized with ``v / max(||v||, eps)``.

    Zero image direction (stylized == source, e.g. at step 0): the normalized
    direction is the zero vector, so cos = 0 and the loss is exactly 1 (no
    NaN). The gradient there w.r.t. the image direction is ``-t̂ / (B * eps)``
    (``t̂`` the unit text direction): finite (norm ``1/(B*eps)`` = 1e4/B for the
    default ``eps=1e-4``) and pointing exactly along the text direction, so the
    first optimizer step moves the image embedding towards the target style.
    Once ``||v|| > eps`` this is the exact cosine and its usual gradient.
    (If target and source prompts embed identically the text direction is 0
    and the loss is the constant 1: validate prompts once, not per step.)

    Args:
        img_emb: ``[B, D]`` embeddings of stylized renders.
        src_img_emb: ``[B, D]`` embeddings of the matching source renders
            (usually computed without grad).
        tgt_txt_emb: ``[D]`` target prompt embedding.
        src_txt_emb: ``[D]`` source prompt embedding.
        eps: direction-normalization epsilon (see above).
    Returns: 0-dim tensor in [0, 2].
    """
    _check_2d(img_emb, "img_emb")
    _check_2d(src_img_emb, "src_img_emb")
    if src_img_emb.shape != img_emb.shape:
        raise ValueError(f"src_img_emb {tuple(src_img_emb.shape)} must match img_emb {tuple(img_emb.shape)}")
    img_dir = F.normalize(_unit(img_emb) - _unit(src_img_emb), dim=-1, eps=eps)
    txt_dir = _unit(_as_row(tgt_txt_emb, "tgt_txt_emb")) - _unit(_as_row(src_txt_emb, "src_txt_emb"))
    txt_dir = F.normalize(txt_dir, dim=-1, eps=eps)
    cos = (img_dir * txt_dir).sum(-1)
    return (1.0 - cos).mean()


def contrastive_loss(query: Tensor, positive: Tensor, negatives: Tensor, tau: float = 0.07) -> Tensor:
    """Eq. 5 (InfoNCE), mean over queries of
    ``-log( exp(q·p/τ) / (exp(q·p/τ) + Σ_m exp(q·n_m/τ)) )``.

    All embeddings are L2-normalized, so ``q·p`` is a cosine. Computed as a
    cross-entropy over the logits ``[q·p, q·n_1, ..., q·n_M] / τ`` (a
    logsumexp), which is stable for any τ > 0 (tested down to 1e-3 with
    identical and antipodal embeddings).

    Args:
        query: ``[B, D]`` image (or patch) embeddings of stylized renders.
        positive: ``[D]`` (shared) or ``[B, D]`` (per query) positive embeddings,
            e.g. the target prompt's text embedding.
        negatives: ``[M, D]`` negative embeddings (M >= 1), e.g. negative prompts.
        tau: temperature τ > 0 (paper: 0.07).
    Returns: 0-dim tensor >= 0.
    """
    _check_2d(query, "query")
    _check_2d(negatives, "negatives")
    if tau <= 0:
        raise ConfigError(f"contrastive_loss: temperature tau must be > 0, got {tau}")
    q = _unit(query)
    if positive.dim() == 2 and positive.shape[0] == q.shape[0] and q.shape[0] > 1:
        p = _unit(positive)
    else:
        p = _unit(_as_row(positive, "positive"))
    pos = (q * p).sum(-1, keepdim=True)  # [B,1]
    with torch.autocast(q.device.type, enabled=False):  # as precise as pos under trainer.precision=*-mixed
        neg = q @ _unit(negatives).to(q.dtype).t()  # [B,M]
    logits = torch.cat([pos, neg], dim=1) / tau
    target = torch.zeros(q.shape[0], dtype=torch.long, device=q.device)
    return F.cross_entropy(logits, target)


def weight_regularization(weights: Tensor, depths: Tensor) -> Tensor:
    """Eq. 7: mean over rays of ``Σ_i Σ_j w_i w_j |d_i - d_j|``.

    Penalizes weight spread along each ray (cloudy artifacts). Computed in
    O(K log K) per ray (a sort, only if the depths are not already ascending)
    plus O(K) prefix sums: with depths ascending,
    ``Σ_{i,j} w_i w_j |d_i - d_j| = 2 Σ_j w_j (d_j W_{<j} - S_{<j})`` where
    ``W_{<j} = Σ_{i<j} w_i`` and ``S_{<j} = Σ_{i<j} w_i d_i`` (exclusive
    cumsums). Autograd through this form gives exactly the gradients of the
    O(K²) double sum wherever depths are distinct (at ties |·| is not
    differentiable anyway).

    Args:
        weights: ``[R, K]`` volume-rendering weights (Eq. 1).
        depths: ``[R, K]`` sample depths (e.g. interval mid-points), any units.
    Returns: 0-dim tensor, units of ``depths``.
    """
    if weights.shape != depths.shape or weights.dim() != 2:
        raise ValueError(
            f"weights and depths must both be [R, K], got {tuple(weights.shape)} and {tuple(depths.shape)}"
        )
    if weights.shape[1] > 1 and bool((depths[:, 1:] < depths[:, :-1]).any()):
        depths, order = torch.sort(depths, dim=1)
        weights = torch.gather(weights, 1, order)
    wd = weights * depths
    w_before = torch.cumsum(weights, dim=1) - weights  # exclusive prefix sums
    wd_before = torch.cumsum(wd, dim=1) - wd
    per_ray = 2.0 * (weights * (depths * w_before - wd_before)).sum(dim=1)
    return per_ray.mean()


def perceptual_loss(
    feats_a: Sequence[Tensor], feats_b: Sequence[Tensor], weights: Sequence[float] | None = None
) -> Tensor:
    """Eq. 9: ``||φ(I_tgt) - φ(I_src)||²`` summed over layers, as a weighted mean.

    Per layer: the mean squared difference over all elements (MSE, i.e. the
    paper's squared L2 norm divided by the element count, so layers of
    different sizes are comparable). Layers are combined as
    ``Σ_l w_l mse_l / Σ_l w_l`` (plain mean over layers if ``weights`` is None).

    Args:
        feats_a: per-layer features of the stylized render, e.g. ``[B, C_l, H_l, W_l]``.
        feats_b: matching features of the source render (usually no grad).
        weights: optional per-layer non-negative weights.
    Returns: 0-dim tensor >= 0.
    """
    if len(feats_a) != len(feats_b) or len(feats_a) == 0:
        raise ValueError(f"perceptual_loss needs equally many (>0) layers, got {len(feats_a)} and {len(feats_b)}")
    if weights is None:
        weights = [1.0] * len(feats_a)
    if len(weights) != len(feats_a):
        raise ConfigError(f"perceptual_loss: {len(weights)} layer weights for {len(feats_a)} layers")
    total_w = float(sum(weights))
    if total_w <= 0:
        raise ConfigError(f"perceptual_loss: layer weights must sum to > 0, got {list(weights)}")
    loss = feats_a[0].new_zeros(())
    for fa, fb, w in zip(feats_a, feats_b, weights):
        if fa.shape != fb.shape:
            raise ValueError(f"perceptual_loss: feature shapes differ {tuple(fa.shape)} vs {tuple(fb.shape)}")
        loss = loss + w * F.mse_loss(fa, fb)
    return loss / total_w


def reconstruction_loss(rgb: Tensor, target: Tensor, mask: Tensor | None = None) -> Tensor:
    """Eq. 2: mean squared colour error over rays (and channels).

    Args:
        rgb: ``[R, 3]`` rendered colours in [0, 1].
        target: ``[R, 3]`` ground-truth colours.
        mask: optional ``[R]`` (bool or float weights in [0, 1]); only masked
            rays count: ``Σ m_r ||c_r - ĉ_r||² / (3 Σ m_r)``. All-zero mask -> 0.
    Returns: 0-dim tensor.
    """
    if rgb.shape != target.shape:
        raise ValueError(f"rgb {tuple(rgb.shape)} and target {tuple(target.shape)} differ")
    se = (rgb - target) ** 2
    if mask is None:
        return se.mean()
    m = mask.to(se.dtype).reshape(se.shape[0], *([1] * (se.dim() - 1)))
    denom = m.sum() * (se[0].numel() if se.dim() > 1 else 1)
    return (se * m).sum() / denom.clamp_min(1e-8)


def silhouette_loss(opacity: Tensor, target: Tensor) -> Tensor:
    """Binary cross-entropy of ray opacities [R] against a target silhouette [R] in [0,1]: the mask
    term of the reconstruction (against the photos' mattes), and while stylizing against the source
    render's opacity (keeps a colour-only style from growing the object over the background).
    Opacities are clamped to [1e-4, 1 - 1e-4]. Returns a 0-dim mean."""
    if opacity.shape != target.shape or opacity.dim() != 1:
        raise ValueError(f"silhouette_loss expects opacity and target [R], got {tuple(opacity.shape)} "
                         f"and {tuple(target.shape)}")
    return F.binary_cross_entropy(opacity.float().clamp(1e-4, 1.0 - 1e-4), target.float().clamp(0.0, 1.0))


def psnr(rgb: Tensor, target: Tensor, mask: Tensor | None = None, max_val: float = 1.0) -> Tensor:
    """Peak signal-to-noise ratio in dB: ``10 log10(max_val² / MSE)``.

    MSE as in :func:`reconstruction_loss` (mask-aware), clamped at 1e-10 so a
    perfect match reads 100 dB (for max_val=1) instead of inf.
    """
    mse = reconstruction_loss(rgb.detach(), target.detach(), None if mask is None else mask.detach())
    return 10.0 * torch.log10(max_val**2 / mse.clamp_min(1e-10))


def nnfm_loss(feats: Sequence[Tensor], style_feats: Sequence[Tensor], mask: Tensor | None = None) -> Tensor:
    """ARF's nearest-neighbour feature matching (Zhang et al., *ARF*, ECCV 2022): each rendered feature vector's
    cosine distance to its nearest feature vector of the style picture, averaged over the view, then over layers.

    Args:
        feats: per-layer features of the rendered view, ``[1, C_l, H_l, W_l]``.
        style_feats: the style picture's features at the same layers, ``[1, C_l, h_l, w_l]`` (any size).
        mask: optional ``[H, W]`` weights in [0, 1] of the view's pixels (the subject): each layer's locations
            are weighted by its area-average; an all-zero mask gives 0.
    Returns: 0-dim tensor in [0, 2].
    """
    if len(feats) != len(style_feats) or len(feats) == 0:
        raise ValueError(f"nnfm_loss needs equally many (>0) layers, got {len(feats)} and {len(style_feats)}")
    loss = feats[0].new_zeros(())
    for f, s in zip(feats, style_feats):
        if f.dim() != 4 or s.dim() != 4 or f.shape[0] != 1 or s.shape[:2] != f.shape[:2]:
            raise ValueError(f"nnfm_loss: features [1,C,H,W] with equal C, got {tuple(f.shape)} and {tuple(s.shape)}")
        a = F.normalize(f[0].flatten(1).T.float(), dim=-1)  # [HW, C]
        b = F.normalize(s[0].flatten(1).T.float(), dim=-1)  # [hw, C]
        nearest = (1.0 - a @ b.T).min(dim=1).values  # [HW]
        if mask is None:
            loss = loss + nearest.mean()
            continue
        w = F.adaptive_avg_pool2d(mask.float()[None, None], f.shape[-2:]).flatten()
        loss = loss + (nearest * w).sum() / w.sum().clamp_min(1e-8)
    return loss / len(feats)


def gram_matrix(feats: Tensor, mask: Tensor | None = None) -> Tensor:
    """The Gram matrix ``[C, C]`` of features ``[1, C, H, W]`` (Gatys et al.): the mean over locations of the outer
    products of the feature vectors; ``mask`` ``[H, W]`` weights the locations as in :func:`nnfm_loss`."""
    if feats.dim() != 4 or feats.shape[0] != 1:
        raise ValueError(f"gram_matrix: features [1,C,H,W], got {tuple(feats.shape)}")
    x = feats[0].flatten(1).float()  # [C, HW]
    if mask is None:
        return x @ x.T / x.shape[1]
    w = F.adaptive_avg_pool2d(mask.float()[None, None], feats.shape[-2:]).flatten()
    return (x * w) @ x.T / w.sum().clamp_min(1e-8)


def colour_loss(img: Tensor, target: Tensor, cell: int = 4) -> Tensor:
    """The mean squared difference of two images' local colours: their means over ``cell`` x ``cell`` pixel cells
    (``img``, ``target`` ``[B, 3, H, W]``), so the palette is pulled toward ``target`` and not the detail."""
    if img.shape != target.shape or img.dim() != 4:
        raise ValueError(f"colour_loss expects two images [B,3,H,W] of one shape, got {tuple(img.shape)} and "
                         f"{tuple(target.shape)}")
    return F.mse_loss(F.avg_pool2d(img, cell, ceil_mode=True), F.avg_pool2d(target, cell, ceil_mode=True))
