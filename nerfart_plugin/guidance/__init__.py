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
    vgg:  {weights: DEFAULT, layers: [relu1_2, relu2_2, relu3_3, relu4_3], max_size: null}
    toy:  {num_structure: 8, structure_scale: 0.5, input_size: 64}
"""

from __future__ import annotations

from collections.abc import Mapping
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


def _plain(cfg: Any) -> dict[str, Any]:
    if cfg is None:
        return {}
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    except ImportError:  # pragma: no cover
        pass
    if isinstance(cfg, Mapping):
        return {k: _plain(v) if isinstance(v, Mapping) else v for k, v in cfg.items()}
    raise ConfigError(f"guidance config must be a mapping, got {type(cfg).__name__}")


def build_guidance(cfg: Any) -> Guidance:
    """Build the guidance encoder named ``cfg["name"]`` (see module docstring for keys)."""
    c = _plain(cfg)
    name = c.get("name", "clip")
    cls = registry.get("guidance", name)  # ConfigError listing valid names
    if cls is CLIPGuidance:
        sub = dict(c.get("clip") or {})
        return CLIPGuidance(
            allow_random_weights=bool(c.get("allow_random_weights", False)),
            allow_download=c.get("allow_download"),
            **sub,
        )
    sub = dict(c.get(name) or {})
    try:
        return cls(**sub)
    except TypeError as exc:
        raise ConfigError(f"guidance.{name} has invalid keys {sorted(sub)}: {exc}") from exc


def build_perceptual(cfg: Any) -> nn.Module:
    """Perceptual feature extractor for Eq. 9: :class:`Perceptual` (VGG16) or the toy
    :class:`EdgePerceptual` (default for ``name: toy``). Both expose
    ``features(img [B,3,H,W] in [0,1]) -> list[Tensor]`` and ``is_real``."""
    c = _plain(cfg)
    defaults = {"toy": "edges", "imagenet": "imagenet"}
    kind = c.get("perceptual") or defaults.get(c.get("name", "clip"), "vgg")
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
        return Perceptual(
            allow_random_weights=bool(c.get("allow_random_weights", False)),
            allow_download=c.get("allow_download"),
            **sub,
        )
    except TypeError as exc:
        raise ConfigError(f"guidance.vgg has invalid keys {sorted(sub)}: {exc}") from exc
