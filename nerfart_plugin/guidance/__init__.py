"""Guidance: CLIP / toy encoders, VGG perceptual features, prompts and negatives.

Registry kind "guidance": "clip" (:class:`~.clip.CLIPGuidance`), "toy"
(:class:`~.toy.ToyGuidance`), "imagenet" (:class:`~.imagenet.ImageNetGuidance`, a
verification guide: a real ImageNet classifier standing in for CLIP; needs the
``imagenet`` extra, imported on first use). Build from config with :func:`build_guidance`
and :func:`build_perceptual`.

Config (dict or OmegaConf) keys and defaults::

    name: clip                    # clip | toy | imagenet
    allow_random_weights: false   # tests only: random CLIP/VGG weights
    allow_download: null          # null -> env NERFART_ALLOW_DOWNLOAD
    perceptual: null              # null -> vgg for clip, edges for toy, imagenet for imagenet;
                                  # or vgg | edges | imagenet (Lite0's first stages)
    clip: {model: ViT-B-32, pretrained: openai, cache_dir: null, quick_gelu: null,
           resize_mode: squash, model_overrides: null}
    vgg:  {weights: DEFAULT, layers: [relu1_2, relu2_2, relu3_3, relu4_3], max_size: null, precision: auto}
    toy:  {num_structure: 8, structure_scale: 0.5, input_size: 64}
"""

from __future__ import annotations

from typing import Any

from torch import nn

from nerfart_plugin import registry
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.guidance import clip, toy  # noqa: F401  (registers "clip", "toy")
from nerfart_plugin.guidance.base import Guidance
from nerfart_plugin.guidance.clip import CLIPGuidance
from nerfart_plugin.guidance.patches import random_patches
from nerfart_plugin.guidance.prompts import (
    NegativeSampler,
    augment_prompt,
    default_source_prompt,
    load_negatives,
    resolve_negatives,
    validate_prompt,
)
from nerfart_plugin.guidance.toy import ToyGuidance
from nerfart_plugin.guidance.vgg import EdgePerceptual, Perceptual

__all__ = [
    "Guidance",
    "CLIPGuidance",
    "ToyGuidance",
    "Perceptual",
    "EdgePerceptual",
    "NegativeSampler",
    "augment_prompt",
    "default_source_prompt",
    "load_negatives",
    "resolve_negatives",
    "validate_prompt",
    "random_patches",
    "build_guidance",
    "build_perceptual",
]


def _common(cfg: Any) -> tuple[Any, dict[str, Any]]:
    """The keys every guidance shares (typed: :class:`~nerfart_plugin.schema.GuidanceCommon`) and the config."""
    from nerfart_plugin.schema import GuidanceCommon, section, to_plain

    c = to_plain(cfg)
    return section(GuidanceCommon, c, prefix="guidance"), c


def build_guidance(cfg: Any) -> Guidance:
    """Build the guidance encoder named ``cfg["name"]`` (see module docstring for keys)."""
    common, c = _common(cfg)
    cls = registry.get("guidance", common.name)  # ConfigError listing valid names
    if cls is CLIPGuidance:
        return CLIPGuidance(allow_random_weights=common.allow_random_weights, allow_download=common.allow_download,
                            **dict(c.get("clip") or {}))
    sub = dict(c.get(common.name) or {})
    try:
        return cls(**sub)
    except TypeError as exc:
        raise ConfigError(f"guidance.{common.name} has invalid keys {sorted(sub)}: {exc}") from exc


def build_perceptual(cfg: Any) -> nn.Module:
    """Perceptual feature extractor for Eq. 9: :class:`Perceptual` (VGG16) or the toy
    :class:`EdgePerceptual` (default for ``name: toy``). Both expose
    ``features(img [B,3,H,W] in [0,1]) -> list[Tensor]`` and ``is_real``."""
    common, c = _common(cfg)
    kind = common.perceptual or {"toy": "edges", "imagenet": "imagenet"}.get(common.name, "vgg")
    if kind == "edges":
        return EdgePerceptual(**dict(c.get("edges") or {}))
    if kind == "imagenet":
        from nerfart_plugin.guidance.imagenet import LitePerceptual

        sub = dict(c.get("lite_perceptual") or {})
        try:
            return LitePerceptual(**{k: (tuple(v) if k == "stages" else v) for k, v in sub.items()})
        except TypeError as exc:
            raise ConfigError(f"guidance.lite_perceptual has invalid keys {sorted(sub)}: {exc}") from exc
    if kind != "vgg":
        raise ConfigError(f"guidance.perceptual={kind!r}; use vgg, edges or imagenet")
    sub = dict(c.get("vgg") or {})
    try:
        return Perceptual(allow_random_weights=common.allow_random_weights, allow_download=common.allow_download,
                          **sub)
    except TypeError as exc:
        raise ConfigError(f"guidance.vgg has invalid keys {sorted(sub)}: {exc}") from exc
