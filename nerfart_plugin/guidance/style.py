"""The style of a stylization: its guide and perceptual network (frozen), the prompts as typed and as the guide
reads them, the negatives, the style picture and its feature network, and the stamp its outputs carry when the guide
is not a real CLIP.

:func:`build_style` builds it from a run's config first, so that missing weights, a prompt the guide cannot take
or a missing negatives file stop a run before any training (:func:`check_style`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Optional

import torch

from nerfart_plugin.config.validate import parse_config
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.guidance import (augment_prompt, build_guidance, build_perceptual, default_source_prompt,
    negatives_origin, resolve_negatives, validate_prompt)
from nerfart_plugin.guidance.style_image import StyleImage, style_features, style_layers

log = logging.getLogger("nerfart_plugin")


@dataclass
class Style:
    """The guidance of a stylization: the prompt, the style picture, or both.

    Attributes:
        guidance / perceptual: the frozen encoders (CLIP + VGG, toy, imagenet); ``guidance`` is None without a
            prompt (a picture alone needs no guide).
        real: the networks used are real pretrained models (else the outputs are stamped).
        stamp: suffix of every output file ("" for real CLIP; ``_UNSTYLED-toy``, ``_VERIFY-imagenet``).
        raw_prompt / prompt: the prompt as typed / after augmentation (None: a picture alone);
        source_prompt: Eq. 4's t_src.
        negatives: ``(stylize.negatives, the resolved negative prompts)`` once :func:`check_style` resolved
            them, so the stylization does not resolve them again; None before.
        image / features: the style picture (``style_image``) and the network whose features are matched to it
            (:mod:`~nerfart_plugin.guidance.style_image`); None without a picture.
    """

    guidance: Any
    perceptual: Any
    real: bool
    stamp: str
    raw_prompt: Optional[str]
    prompt: Optional[str]
    source_prompt: str
    negatives: Optional[tuple[str, list]] = None
    image: Optional[StyleImage] = None
    features: Any = None

    @property
    def name(self) -> str:
        """What the style is called in folder names and logs: the prompt, the picture's file stem, or both."""
        parts = [self.raw_prompt, self.image.name if self.image is not None else None]
        return " + ".join(p for p in parts if p)

    @property
    def text(self) -> bool:
        """A prompt guides the run (the text terms of Eq. 8 apply)."""
        return self.prompt is not None

    @property
    def warning(self) -> Optional[str]:
        """The ``WARNING`` of a stylization's ``metrics.json`` when the guide is not a real CLIP (None when it is)."""
        if self.stamp.startswith("_VERIFY"):
            return ("VERIFICATION run: guided by an ImageNet classifier standing in for CLIP, not by CLIP; see the "
                    "judge block")
        if not self.real:
            return "UNSTYLED by a real model: random or toy guidance weights were used"
        return None


def build_style(cfg: Any, guidance: Any = None, perceptual: Any = None) -> Style:
    """Build the guidance of ``cfg`` (first, so missing weights and a bad style picture fail before any training)
    and resolve the prompts: augmentation (``prompt_augment``), ``source_prompt=auto`` from ``data.subject``."""
    c, _ = parse_config(cfg)
    g = c.guidance
    if c.prompt is None and not c.style_image.given:
        raise ConfigError("a stylization needs a style: add +prompt=\"Vincent van Gogh\" or +style_image=<picture.png> "
                          "(or both).")
    image = StyleImage.load(c.style_image.file, c.style_image.size) if c.style_image.given else None
    if c.prompt is None:  # a picture alone needs no guide
        guidance = None
    elif guidance is None:
        guidance = build_guidance(g)
    perceptual = perceptual if perceptual is not None else build_perceptual(g)
    features = style_features(c) if image is not None else None
    nets = [n for n in (guidance, perceptual, features) if n is not None]
    real = all(getattr(n, "is_real", True) for n in nets)
    own_stamp = guidance.output_stamp() if guidance is not None else ""
    stamp = own_stamp or ("" if real else f"_UNSTYLED-{g.name}")
    if not real:
        log.warning("guidance is not a real pretrained model (%s): every output is stamped %r", g.name, stamp)
    raw = validate_prompt(c.prompt) if c.prompt is not None else None
    prompt = augment_prompt(raw) if raw is not None and c.prompt_augment else raw
    if prompt != raw:
        log.info("prompt augmented: %r -> %r", raw, prompt)
    src = c.source_prompt if c.source_prompt != "auto" else default_source_prompt(getattr(c.data, "subject", None) or "object")
    return Style(guidance, perceptual, real, stamp, raw, prompt, src, image=image, features=features)


def check_style(style: Style, negatives: str) -> None:
    """What stylization will resolve, resolved now, before any training: the prompts in the guide's terms
    (``guidance=imagenet`` needs an ImageNet class) and the negative prompts (``stylize.negatives``: a
    file must exist and parse). Raises the ConfigError the stylization would raise later. Nothing to resolve
    without a prompt."""
    if not style.text:
        style.negatives = (negatives, [])
        return
    with torch.no_grad():
        style.guidance.encode_text([style.prompt])
    style.negatives = (negatives, resolve_negatives(negatives, style.guidance, style.prompt))


def negatives_of(style: Style, spec: str) -> list:
    """The negative prompts ``spec`` (``stylize.negatives``) names for ``style``: as :func:`check_style` resolved
    them when it did so for the same spec, else resolved now."""
    if style.negatives is not None and style.negatives[0] == spec:
        return style.negatives[1]
    if not style.text:
        return []
    return resolve_negatives(spec, style.guidance, style.prompt)


def style_choices(style: Style, settings: Any, cfg: Any = None) -> dict[str, Any]:
    """What the style's ``auto`` settings became (:mod:`nerfart_plugin.config.auto`): the source prompt, the view size,
    the negatives (where they came from and how many) and the threshold that excludes near-synonyms; with a style
    picture, the network and layers its features come from."""
    out: dict[str, Any] = {"stylize.resolution": settings.resolution}
    if style.text:
        spec = settings.negatives
        out.update({"source_prompt": style.source_prompt,
                    "stylize.negatives": f"{negatives_origin(spec, style.guidance)}: {len(negatives_of(style, spec))} prompts",
                    "stylize.negative_threshold": settings.negative_threshold})
    if style.image is not None and cfg is not None:
        family, layers = style_layers(cfg)
        out["style_image.layers"] = f"{family}: {', '.join(layers) or 'its own'}"
    return out
