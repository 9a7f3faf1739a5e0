"""Guidance: CLIP / toy encoders, VGG perceptual features, prompts and negatives.

Registry kind "guidance": "clip" (:class:`~.clip.CLIPGuidance`), "toy"
(:class:`~.toy.ToyGuidance`), "imagenet" (:class:`~.imagenet.ImageNetGuidance`, a
verification guide: a real ImageNet classifier standing in for CLIP; needs the
``imagenet`` extra, imported on first use). Build from config with :func:`build_guidance`
and :func:`build_perceptual`.

Each guide and perceptual network declares its settings beside it (``Config``, whose ``section`` names
its sub-section); the section's common keys become one :class:`WeightsPolicy`. Keys and defaults::

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

from nerfart_plugin.config import registry
from nerfart_plugin.config.sections import typed_section
from nerfart_plugin.guidance import clip, toy  # noqa: F401  (registers "clip", "toy")
from nerfart_plugin.guidance.base import Guidance, WeightsPolicy
from nerfart_plugin.guidance.clip import CLIPGuidance
from nerfart_plugin.guidance.patches import random_patches
from nerfart_plugin.guidance.prompts import (NegativeSampler, augment_prompt, default_negative_threshold,
    default_source_prompt, load_negatives, negatives_origin, resolve_negatives, validate_prompt)
from nerfart_plugin.guidance.toy import ToyGuidance
from nerfart_plugin.guidance.vgg import EdgePerceptual, Perceptual

__all__ = [
    "Guidance",
    "CLIPGuidance",
    "ToyGuidance",
    "Perceptual",
    "EdgePerceptual",
    "NegativeSampler",
    "default_negative_threshold",
    "negatives_origin",
    "augment_prompt",
    "default_source_prompt",
    "load_negatives",
    "resolve_negatives",
    "validate_prompt",
    "random_patches",
    "build_guidance",
    "build_perceptual",
    "WeightsPolicy",
]


def build_guidance(cfg: Any) -> Guidance:
    """Build the guide of the ``guidance`` section (``cfg``: typed or a mapping; ``name`` picks the guide, its
    settings are the section's, checked by its ``Config``) with the section's weights policy."""
    g = typed_section("guidance", cfg)
    cls = registry.get("guidance", g.name)
    return cls(g, policy=WeightsPolicy(g.allow_random_weights, g.allow_download))


def perceptual_section(cfg: Any) -> Any:
    """The typed ``guidance.perceptual`` section of the ``guidance`` section ``cfg``: as given, else the guide's
    ``default_perceptual``."""
    g = typed_section("guidance", cfg)
    return g.perceptual or typed_section("guidance.perceptual", registry.get("guidance", g.name).default_perceptual)


def build_perceptual(cfg: Any, **update: Any) -> nn.Module:
    """The feature network of Eq. 9 (registry kind ``perceptual``: ``vgg`` :class:`Perceptual`, ``edges``
    :class:`EdgePerceptual`, ``imagenet`` Lite0's first stages): ``guidance.perceptual``, else the guide's
    ``default_perceptual``, with the settings ``update`` (the style picture's layers). Each exposes
    ``features(img [B,3,H,W] in [0,1]) -> list[Tensor]`` and ``is_real``."""
    g = typed_section("guidance", cfg)
    p = perceptual_section(g)
    if update:
        p = typed_section("guidance.perceptual", {**p.model_dump(mode="json"), **update})
    cls = registry.get("perceptual", p.name)
    return cls(p, policy=WeightsPolicy(g.allow_random_weights, g.allow_download))
