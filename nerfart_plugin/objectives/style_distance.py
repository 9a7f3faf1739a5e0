"""How close renders came to a style picture (``style_image``), measured with a network that did not guide.

:func:`style_image_metrics`: on the subject's pixels of the held-out views, source vs stylized, the Gram-matrix
distance (Gatys et al.; relative Frobenius) and the nearest-neighbour feature distance (ARF's NNFM) to the
picture with the judge's EfficientNet-Lite2 features (blocks :data:`STYLE_JUDGE_BLOCKS`), never the guide's
network, and the colour distance (:func:`colour_distance`: Earth mover's per CIE Lab channel). Lower is closer.
"""

from __future__ import annotations

from typing import Any

import torch

from nerfart_plugin.errors import WeightsMissingError
from nerfart_plugin.guidance.imagenet import LitePerceptual
from nerfart_plugin.objectives.losses import gram_matrix, nnfm_loss

#: the judge's blocks whose features measure a style distance (never the guide's network: Lite2, not Lite0)
STYLE_JUDGE_BLOCKS = (1, 2, 3)


def style_image_metrics(picture: torch.Tensor, source: torch.Tensor, stylized: torch.Tensor,
                        source_masks: torch.Tensor, stylized_masks: torch.Tensor) -> dict[str, Any]:
    """How close the held-out views [B,3,H,W] in [0,1] of source and stylization are to a style ``picture``
    [3,h,w], on the subject's pixels (``*_masks`` [B,H,W], opacity): per view then averaged, the Gram distance
    (relative Frobenius, mean over :data:`STYLE_JUDGE_BLOCKS`), the NNFM distance (mean nearest cosine distance)
    with the judge's Lite2 features, and the colour distance (Earth mover's per Lab channel, summed). ``skipped``
    says why when the judge's network is not installed."""
    try:
        net = LitePerceptual(model="lite2", stages=STYLE_JUDGE_BLOCKS).to(source.device)
    except (ImportError, WeightsMissingError) as exc:  # the judge is optional (the imagenet extra)
        return {"skipped": f"the judge's network is not installed ({exc})"}
    with torch.no_grad():
        ref = net.features(picture[None].to(source.device))
        grams = [gram_matrix(f) for f in ref]
        out: dict[str, Any] = {"network": f"efficientnet-lite2 blocks {list(STYLE_JUDGE_BLOCKS)}"}
        for name, views, masks in (("source", source, source_masks), ("stylized", stylized, stylized_masks)):
            gram, nnfm = [], []
            for img, mask in zip(views, masks):
                feats = net.features(img[None])
                gram.append(float(sum((gram_matrix(f, mask) - g).norm() / g.norm() for f, g in zip(feats, grams))
                                  / len(grams)))
                nnfm.append(float(nnfm_loss(feats, ref, mask=mask)))
            out[f"gram_{name}"] = sum(gram) / len(gram)
            out[f"nnfm_{name}"] = sum(nnfm) / len(nnfm)
            out[f"colour_emd_{name}"] = colour_distance(views, masks, picture)
    return out


def colour_distance(views: torch.Tensor, masks: torch.Tensor, picture: torch.Tensor) -> float:
    """Earth mover's distance between the colours of the views' subject pixels (``masks`` > 0.5) and the picture's,
    per CIE Lab channel (scipy), summed over L, a, b."""
    from scipy.stats import wasserstein_distance
    from skimage.color import rgb2lab

    pixels = views.permute(0, 2, 3, 1)[masks > 0.5].detach().cpu().double().numpy()
    if len(pixels) == 0:
        return float("nan")
    ref = picture.permute(1, 2, 0).reshape(-1, 3).detach().cpu().double().numpy()
    a, b = rgb2lab(pixels[None])[0], rgb2lab(ref[None])[0]
    return float(sum(wasserstein_distance(a[:, c], b[:, c]) for c in range(3)))
