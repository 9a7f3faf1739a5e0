"""Every metric of a run: reconstruction quality (PSNR, masked PSNR, SSIM) and the stylization
metrics (CLIP score, CLIP directional similarity, view consistency, edge similarity, an independent
ImageNet judge, how much rendering weight lies off the surface, silhouette IoU).

* Reconstruction (:func:`view_metrics`, :func:`mean_metrics`): PSNR (dB) and SSIM
  (kornia, 11x11 Gaussian window) of each held-out view, PSNR inside the mask where
  the scene has masks, averaged over the views.

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
* Judge (:class:`ImageNetJudge`): an ImageNet classifier that never guides
  (EfficientNet-Lite2) classifies held-out views of source and stylized; when
  the prompt names an ImageNet class, its probability and top-5 rank say
  whether the stylization is recognisable by a network it was not optimized
  against.
* Off-surface weight (:func:`off_surface_weight`): the share of each ray's
  rendering weight farther than ``delta`` from its expected depth: the cloudy
  geometry Eq. 7 suppresses.
* Edge similarity (:func:`edge_similarity`): cosine of Sobel edge magnitudes of
  source and stylized views (1 = same structure; what Eq. 9 keeps).
* Silhouette IoU (:func:`silhouette_iou`): of the opacity masks of source and stylized.
* Style distance to a style picture: :mod:`nerfart_plugin.objectives.style_distance`.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Iterable, Mapping, Optional

import torch
import torch.nn.functional as F

from nerfart_plugin.errors import WeightsMissingError
from nerfart_plugin.guidance.imagenet import VARIANTS, imagenet_classes, lite_preprocess, load_efficientnet_lite
from nerfart_plugin.objectives.losses import psnr

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------- reconstruction
def view_metrics(pred: torch.Tensor, target: torch.Tensor, mask: Optional[torch.Tensor] = None) -> dict[str, float]:
    """PSNR (dB), SSIM (kornia, 11x11 Gaussian window) and, with a mask, PSNR inside the mask.

    ``pred``/``target`` [H,W,3] in [0,1]; ``mask`` [H*W] or [H,W] in [0,1].
    """
    import kornia

    pred, target = pred.clamp(0, 1).float(), target.float()
    out = {"psnr": float(psnr(pred.reshape(-1, 3), target.reshape(-1, 3)))}
    a = pred.permute(2, 0, 1)[None]
    b = target.permute(2, 0, 1)[None]
    out["ssim"] = float(kornia.metrics.ssim(a, b, window_size=11).mean())
    if mask is not None:
        m = mask.reshape(-1).to(pred.device).float() > 0.5
        if m.any():
            out["psnr_masked"] = float(psnr(pred.reshape(-1, 3)[m], target.reshape(-1, 3)[m]))
    return out


def mean_metrics(per_view: Iterable[Mapping[str, float]]) -> dict[str, float]:
    """Each metric averaged over the views that have it (``psnr_masked``: the views with a mask)."""
    per_view = list(per_view)
    keys = sorted(set().union(*per_view)) if per_view else []
    return {k: float(sum(m[k] for m in per_view if k in m) / sum(1 for m in per_view if k in m)) for k in keys}


@torch.no_grad()
def evaluate_views(system: Any, views: Iterable[dict[str, Any]], chunk: int,
                   with_normals: bool = True) -> dict[str, float]:
    """:func:`mean_metrics` of ``system.render_view`` against each view batch's photo, plus ``val_views``."""
    per_view = []
    for batch in views:
        img = system.render_view(batch, chunk=chunk, with_normals=with_normals)
        target = batch["rgb"].reshape(img["rgb"].shape).to(img["rgb"].device)
        per_view.append(view_metrics(img["rgb"], target, batch.get("mask")))
    return {**mean_metrics(per_view), "val_views": len(per_view)}


# ---------------------------------------------------------------------- stylization
def edge_similarity(a: torch.Tensor, b: torch.Tensor) -> float:
    """Cosine similarity of Sobel edge magnitudes of two image batches [B,3,H,W] (1 = same structure)."""
    import kornia

    ea = kornia.filters.sobel(kornia.color.rgb_to_grayscale(a)).flatten(1)
    eb = kornia.filters.sobel(kornia.color.rgb_to_grayscale(b)).flatten(1)
    return float(torch.nn.functional.cosine_similarity(ea, eb, dim=1).mean())


@torch.no_grad()
def clip_scores(guidance, stylized: torch.Tensor, source: torch.Tensor, prompt: str | torch.Tensor,
                source_prompt: str | torch.Tensor) -> dict[str, float]:
    """``stylized``/``source`` [B,3,H,W] in [0,1] renders of the same views; the prompts as text or as
    the guidance's text embeddings [D] (e.g. a source embedding derived from the source views)."""
    e_sty = F.normalize(guidance.encode_image(stylized).float(), dim=-1)
    e_src = F.normalize(guidance.encode_image(source).float(), dim=-1)
    emb = [guidance.encode_text([p])[0] if isinstance(p, str) else p for p in (prompt, source_prompt)]
    t = F.normalize(torch.stack(emb).float().to(e_sty.device), dim=-1)
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


class ImageNetJudge:
    """An independent judge of stylizations toward ImageNet classes (EfficientNet-Lite2, 260 px).

    It is never the guide (``guidance=imagenet`` guides with Lite0), so a rising
    target probability means the change is visible to a network the
    optimization did not see, not an adversarial pattern of the guide.
    """

    def __init__(self, model: str = "lite2", weights: Optional[str] = None) -> None:
        self.model = VARIANTS[model].timm_name
        self.size = VARIANTS[model].input_size
        self.net = load_efficientnet_lite(model, weights)
        self.classes = imagenet_classes()

    @torch.no_grad()
    def probabilities(self, images: torch.Tensor) -> torch.Tensor:
        """Class probabilities [B,1000] of ``images`` [B,3,H,W] in [0,1] (any size)."""

        net = self.net.to(images.device)
        return net(lite_preprocess(images, self.size)).softmax(-1).float()

    def assess(self, images: torch.Tensor, target: int) -> dict[str, Any]:
        """Per view: target probability, its rank (0 = top-1) and the top-1 class; plus the means."""
        p = self.probabilities(images)
        rank = (p > p[:, target : target + 1]).sum(1)
        per_view = [{"target_prob": float(p[i, target]), "target_rank": int(rank[i]),
                     "top1": self.classes.name(int(p[i].argmax())), "top1_prob": float(p[i].max())}
                    for i in range(p.shape[0])]
        return {"mean_target_prob": float(p[:, target].mean()), "top5_rate": float((rank < 5).float().mean()),
                "top1_rate": float((rank < 1).float().mean()), "per_view": per_view}


def judge_for(prompt: str) -> tuple[Optional[ImageNetJudge], int, str]:
    """The judge and the ImageNet class ``prompt`` (as typed) names: ``(judge, target, "")``, or ``(None, -1,
    why)`` when the prompt names no class or the judge cannot load."""

    try:
        target = imagenet_classes().find(prompt)
    except ImportError as exc:  # timm missing
        return None, -1, f"the judge needs timm ({exc}): pip install -e '.[imagenet]'"
    if target is None:
        return None, -1, f"the prompt {prompt!r} names no ImageNet class"
    try:
        return ImageNetJudge(), target, ""
    except WeightsMissingError as exc:
        return None, -1, str(exc)


def judge_prompt(prompt: str, source: torch.Tensor, stylized: torch.Tensor, view_ids: list[int]) -> dict[str, Any]:
    """The independent judge's verdict (:func:`judge_block`) on held-out views [B,3,H,W] in [0,1] when
    ``prompt`` (as typed) names an ImageNet class, else why it did not run (``{"skipped": reason}``)."""
    judge, target, skipped = judge_for(prompt)
    if judge is None:
        return {"skipped": skipped}
    block = judge_block(judge, target, source, stylized, view_ids)
    log.info("judge (%s, held-out views %s): P(%s) %.4f -> %.4f, top-5 %.0f%% -> %.0f%%", block["model"], view_ids,
             block["target_class"], block["source"]["mean_target_prob"], block["stylized"]["mean_target_prob"],
             100 * block["source"]["top5_rate"], 100 * block["stylized"]["top5_rate"])
    return block


def judge_block(judge: ImageNetJudge, target: int, source: torch.Tensor, stylized: torch.Tensor,
                view_ids: list[int]) -> dict[str, Any]:
    """The ``judge`` block of ``metrics.json``: source vs stylized held-out views [B,3,H,W]."""
    src, sty = judge.assess(source, target), judge.assess(stylized, target)
    for block in (src, sty):
        for v, entry in zip(view_ids, block["per_view"]):
            entry["view"] = int(v)
    return {"model": judge.model, "target_class": judge.classes.name(target), "target_index": int(target),
            "views": [int(v) for v in view_ids], "source": src, "stylized": sty,
            "gain_mean_target_prob": sty["mean_target_prob"] - src["mean_target_prob"],
            "gain_top5_rate": sty["top5_rate"] - src["top5_rate"]}


def off_surface_weight(weights: torch.Tensor, t: torch.Tensor, deltas: torch.Tensor, rays_d_norm: torch.Tensor,
                       delta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Rendering weight farther than ``delta`` (world units) from each ray's expected depth.

    Args: ``weights`` [R,K]; ``t`` [R,K] section midpoints (ray parameter); ``deltas`` [R,K]
    section lengths (world); ``rays_d_norm`` [R]; ``delta`` world units.
    Returns: ``(off [R], total [R])``: weight beyond ``delta`` and the ray's opacity.
    """
    total = weights.sum(-1)
    depth = (weights * t).sum(-1) / total.clamp_min(1e-10)
    dist = (t - depth[:, None]).abs() * rays_d_norm[:, None]
    off = (weights * (dist > delta).to(weights.dtype) * (deltas > 0).to(weights.dtype)).sum(-1)
    return off, total


@torch.no_grad()
def off_surface_share(renderer: Any, batch: dict[str, Any], delta: float = 0.05, chunk: int = 8192) -> float:
    """Share of a ray batch's total rendering weight lying farther than ``delta`` (world units; the
    scene is normalized to the unit sphere) from each ray's expected depth (see :func:`off_surface_weight`).
    The weights need no normals: an SDF field skips its gradient (a backward pass per sample), unless its
    opacity reads it."""
    n = batch["rays_o"].shape[0]
    off = total = 0.0
    for s in range(0, n, chunk):
        sub = {k: (v[s : s + chunk] if torch.is_tensor(v) and v.dim() > 0 and v.shape[0] == n else v)
               for k, v in batch.items()}
        out = renderer(sub, with_normals=False)
        o, t = off_surface_weight(out["weights"], out["t"], out["deltas"], sub["rays_d"].norm(dim=-1), delta)
        off += float(o.sum())
        total += float(t.sum())
    return off / total if total > 0 else 0.0


def silhouette_iou(opacity_a: torch.Tensor, opacity_b: torch.Tensor, threshold: float = 0.5) -> float:
    """IoU of the silhouettes (opacity > ``threshold``) of two renders [B,H,W] of the same views
    (1 = the stylization kept the outline; 1 also when both are empty)."""
    a, b = opacity_a > threshold, opacity_b > threshold
    union = int((a | b).sum())
    return float((a & b).sum()) / union if union else 1.0


def evaluation_views(scene: Any) -> str:
    """What the reconstruction's PSNR is measured on: "held-out views", or, when no view is truly held out
    (``data.holdout_every=1``, a one-view capture), a label that says it is a training-view evaluation."""
    train = set(scene.train_ids or range(scene.num_images))
    held = scene.val_ids or scene.train_ids[:1]
    if held and not train & set(held):
        return "held-out views"
    return ("TRAINING views: no view is held out (data.holdout_every, or too few views), so this PSNR measures "
            "the fit to the photos, not new views")


#: silhouette IoU with the source below which a stylization has lost its subject (the stylizations of the
#: benchmarks keep 0.95-0.97)
LOST_SUBJECT_IOU = 0.5


def lost_subject(iou: Optional[float]) -> Optional[str]:
    """The warning for a stylized field whose held-out silhouette kept less than :data:`LOST_SUBJECT_IOU` of the
    source's (its renders show mostly background); None otherwise. Logged too."""
    if iou is None or iou >= LOST_SUBJECT_IOU:
        return None
    text = (f"the stylized field lost its subject: silhouette IoU {iou:.2f} with the source on the held-out views "
            "(the renders show mostly background). Start from a longer reconstruction, lower stylize.lr / "
            "stylize.lr_mlp, or raise experiment.lambda_perceptual")
    log.warning(text)
    return text


# ---------------------------------------------------------------------- inside and outside a region
def region_pixels(mask: Any, batch: dict[str, Any], samples: int = 96) -> torch.Tensor:
    """[H*W] bool: the pixels whose rays meet a region (``mask``: a
    :class:`~nerfart_plugin.fields.composite.RegionMask`; its geometry mask, the larger), sampled at ``samples``
    points between each ray's near and far."""
    o, d = batch["rays_o"].float(), batch["rays_d"].float()
    t = torch.linspace(0, 1, samples, device=o.device)
    near, far = batch["near"].float().reshape(-1, 1), batch["far"].float().reshape(-1, 1)
    ts = near + (far - near) * t[None]
    pts = o[:, None] + d[:, None] * ts[..., None]
    hit = torch.zeros(o.shape[0], dtype=torch.bool, device=o.device)
    for s in range(0, o.shape[0], 4096):
        _, geo = mask(pts[s:s + 4096].reshape(-1, 3))
        hit[s:s + 4096] = (geo.reshape(-1, samples) > 0).any(-1)
    return hit


def box_of(pixels: torch.Tensor) -> Optional[tuple[int, int, int, int]]:
    """``(x0, y0, x1, y1)`` (exclusive ends) of the True pixels of [H,W], or None."""
    ys, xs = torch.nonzero(pixels, as_tuple=True)
    if ys.numel() == 0:
        return None
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def region_metrics(prompt: str, mask: Any, views: list[dict[str, Any]], source: torch.Tensor, stylized: torch.Tensor,
                   view_ids: list[int]) -> dict[str, Any]:
    """How a stylization inside a region changed the held-out views [B,3,H,W] in [0,1] (``views``: their ray
    batches): outside (the pixels whose rays miss the region) the PSNR of the stylized views to the source's and
    the largest pixel change; inside, the judge on each view's crop of the region's projection and the share of
    pixels it covers."""
    outside_sq, outside_n, largest, crops_src, crops_sty, covered, ids = 0.0, 0, 0.0, [], [], [], []
    for i, v, a, b in zip(view_ids, views, source, stylized):
        H, W = int(v["H"]), int(v["W"])
        hit = region_pixels(mask, {k: v[k].to(a.device) for k in ("rays_o", "rays_d", "near", "far")}).reshape(H, W)
        covered.append(float(hit.float().mean()))
        out = ~hit
        if bool(out.any()):
            diff = (a - b)[:, out]
            outside_sq += float(diff.square().sum())
            outside_n += int(diff.numel())
            largest = max(largest, float(diff.abs().max()))
        box = box_of(hit)
        if box is not None:
            x0, y0, x1, y1 = box
            crops_src.append(F.interpolate(a[None, :, y0:y1, x0:x1], size=(H, W), mode="bilinear",
                                           align_corners=False)[0])
            crops_sty.append(F.interpolate(b[None, :, y0:y1, x0:x1], size=(H, W), mode="bilinear",
                                           align_corners=False)[0])
            ids.append(i)
    mse = outside_sq / max(outside_n, 1)
    out: dict[str, Any] = {"outside_psnr_to_source": float(-10 * math.log10(max(mse, 1e-10))),  # 100 dB: identical
                           "outside_max_change": largest, "covered_share": covered}
    if crops_src:
        out["judge_inside"] = judge_prompt(prompt, torch.stack(crops_src), torch.stack(crops_sty), ids)
    return out
