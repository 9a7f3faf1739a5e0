"""Eq. 8's terms as declarative tables: the image terms on the rendered view (with the style picture's, ARF's),
and the per-ray terms on each re-rendered patch (:class:`~nerfart_plugin.systems.stylization.StylizationSystem` weights and sums them).

Each ``fn`` of an image term takes ``(system, ImageInputs)``: the system gives the text embeddings
(``tgt_txt``, ``src_txt``), the settings (``cfg.tau``, ``exp.directional``) and the perceptual network.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

from torch import Tensor

from nerfart_plugin.objectives.losses import (absolute_clip_loss, colour_loss, contrastive_loss,
    directional_clip_loss, nnfm_loss, perceptual_loss, silhouette_loss, weight_regularization)
from nerfart_plugin.systems.loss_terms import LossTerm


@dataclass
class ImageInputs:
    """What the image terms of one step share.

    Attributes:
        img: the rendered view [1,3,H,W] in [0,1] (a leaf: dL/dI is taken w.r.t. it).
        src: the source view's cache entry (:meth:`StylizationSystem.source_view`).
        emb: the guidance embedding of the view [1,D] (None when no term needs it).
        patch_emb: embeddings of the local patches [P,D] (None without the local term).
        negs: the step's negative text embeddings [M,D] (None without contrastive terms).
    """

    img: Tensor
    src: dict[str, Any]
    emb: Optional[Tensor] = None
    patch_emb: Optional[Tensor] = None
    negs: Optional[Tensor] = None


def _directional(s: Any, x: ImageInputs) -> Tensor:
    if s.exp.directional == "absolute":
        return absolute_clip_loss(x.emb, s.tgt_txt)  # Eq. 3
    return directional_clip_loss(x.emb, x.src["emb"], s.tgt_txt, s.src_txt)  # Eq. 4


#: Eq. 8's image terms, on the rendered view (their dL/dI is back-propagated patch by patch).
STYLIZATION_IMAGE_LOSSES: tuple[LossTerm, ...] = (
    LossTerm("dir", _directional, doc="Eq. 4 relative directional CLIP loss (Eq. 3, absolute: experiment.directional)"),
    LossTerm("global", lambda s, x: contrastive_loss(x.emb, s.tgt_txt, x.negs, s.cfg.tau),
             doc="Eq. 5: InfoNCE of the whole view vs the target and negative prompts"),
    LossTerm("local", lambda s, x: contrastive_loss(x.patch_emb, s.tgt_txt, x.negs, s.cfg.tau),
             doc="Eq. 5-6 on local patches (stylize.local_patches of stylize.local_patch_frac of the area)"),
    LossTerm("perceptual", lambda s, x: perceptual_loss(s.perceptual.features(x.img), x.src["feats"]),
             doc="Eq. 9: perceptual distance to the source render"),
)

#: The style picture's terms (``style_image.lambda_<name>``), on the rendered view like Eq. 8's image terms.
STYLE_IMAGE_LOSSES: tuple[LossTerm, ...] = (
    LossTerm("style", lambda s, x: nnfm_loss(s.style_features.features(x.img), s.style_feats, mask=x.src["mask"]),
             doc="ARF's nearest-neighbour feature matching to the style picture, on the subject's pixels"),
    LossTerm("palette", lambda s, x: colour_loss(x.img, x.src["palette"]),
             doc="the local colours pulled toward the source view recoloured to the picture's palette"),
)

#: The per-ray terms, computed with grad on each re-rendered patch; the field's regularizers join them.
STYLIZATION_RAY_LOSSES: tuple[LossTerm, ...] = (
    LossTerm("reg", lambda out, rays: weight_regularization(out["weights"], out["t"]),
             doc="Eq. 7: sum_ij w_i w_j |t_i - t_j| on ray weights (suppresses cloudy geometry)"),
    LossTerm("silhouette", lambda out, rays: silhouette_loss(out["opacity"], rays["source_opacity"]), geometry=True,
             doc="not in Eq. 8: BCE of ray opacity vs the source render's"),
)


def regularizer_term(name: str):
    """The ray term of the field's regularizer ``name`` (its value from the render's ``regularizers``)."""
    return lambda out, rays: out["regularizers"][name]
