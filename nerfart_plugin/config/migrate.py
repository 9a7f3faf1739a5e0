"""The settings layout across versions of the package, so that run folders made before a change keep working.

* **Format 1** (before one config idiom): the data loader was ``data.kind``; a guide's settings lived in a
  sub-section named after it (``guidance.clip.pretrained``), the perceptual network was named by
  ``guidance.perceptual=vgg`` and its settings lived in their own sub-section (``guidance.vgg.weights``,
  ``guidance.lite_perceptual.model``).
* **Format 2** (now): every component section is ``{name, ...its settings}``: ``data.name``,
  ``guidance.pretrained``, ``guidance.perceptual: {name: vgg, weights: ...}``.

:func:`to_current` reads a ``config.yaml`` of either format as format 2 (a run folder's config migrates when it
is opened); :func:`to_format_1` writes a format-2 config in the old layout, which is what the cache keys of runs
made before hashed, so that the same settings find those runs again (:mod:`nerfart_plugin.run.keys`).
"""

from __future__ import annotations

import copy
from typing import Any

#: the layout of the settings that run folders record and cache keys hash (``run.json``'s ``config_format``)
CONFIG_FORMAT = 2

#: format 1: the sub-section of ``guidance`` that held each guide's settings
GUIDE_KEYS_V1 = {"clip": "clip", "imagenet": "imagenet", "toy": "toy"}
#: format 1: the sub-section of ``guidance`` that held each perceptual network's settings
PERCEPTUAL_KEYS_V1 = {"vgg": "vgg", "edges": "edges", "imagenet": "lite_perceptual"}


def config_format(config: dict) -> int:
    """1 for a config in the old layout (``data.kind`` or a guide's sub-section), else 2."""
    data, guidance = config.get("data") or {}, config.get("guidance") or {}
    old_guidance = isinstance(guidance, dict) and (
        isinstance(guidance.get("perceptual"), str)
        or any(isinstance(guidance.get(k), dict) for k in (*GUIDE_KEYS_V1.values(), *PERCEPTUAL_KEYS_V1.values())))
    return 1 if (isinstance(data, dict) and "kind" in data) or old_guidance else 2


def to_current(config: dict) -> dict:
    """``config`` (a run's settings as plain data, either format) in the current layout; a copy."""
    out = copy.deepcopy(config)
    if config_format(out) == 2:
        return out
    data = out.get("data")
    if isinstance(data, dict) and "kind" in data:
        out["data"] = {"name": data.pop("kind"), **data}
    if isinstance(out.get("guidance"), dict):
        out["guidance"] = _guidance_to_current(out["guidance"])
    return out


def _guidance_to_current(g: dict) -> dict:
    name = g.get("name")
    perceptual = g.get("perceptual")
    out = {k: v for k, v in g.items() if not isinstance(v, dict) and k != "perceptual"}
    guide_key = GUIDE_KEYS_V1.get(name, name)
    out.update(g.get(guide_key) or {})
    if isinstance(perceptual, str):
        out["perceptual"] = {"name": perceptual, **(g.get(PERCEPTUAL_KEYS_V1.get(perceptual, perceptual)) or {})}
    return out


def to_format_1(config: dict) -> dict:
    """``config`` (current layout) in format 1's layout: what a cache key of a run made before hashed."""
    out = copy.deepcopy(config)
    data = out.get("data")
    if isinstance(data, dict) and "name" in data:
        out["data"] = {"kind": data.pop("name"), **data}
    g = out.get("guidance")
    if isinstance(g, dict):
        out["guidance"] = guidance_format_1(g)
    return out


def guidance_format_1(g: dict) -> dict:
    """The ``guidance`` section (current layout, as given) in format 1's layout."""
    common = ("name", "allow_random_weights", "allow_download")
    out: dict[str, Any] = {k: g[k] for k in common if k in g}
    settings = {k: v for k, v in g.items() if k not in (*common, "perceptual")}
    if settings:
        out[GUIDE_KEYS_V1.get(g.get("name"), g.get("name"))] = settings
    perceptual = g.get("perceptual")
    if isinstance(perceptual, dict):
        out["perceptual"] = perceptual.get("name")
        rest = {k: v for k, v in perceptual.items() if k != "name"}
        if rest:
            out[PERCEPTUAL_KEYS_V1.get(perceptual.get("name"), perceptual.get("name"))] = rest
    elif perceptual is not None:
        out["perceptual"] = perceptual
    return out
