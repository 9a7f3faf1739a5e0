"""The component sections of a run's config (``data``, ``backbone``, ``encoding``, ``guidance``), checked by
the ``Config`` declared beside the component each names (:mod:`nerfart_plugin.config.components`): the registry
says which component, its Config which settings, types, ranges and meanings."""

from __future__ import annotations

import functools
from typing import Any, Callable, Literal, Optional, Union

from pydantic import BaseModel, ConfigDict, ValidationError, create_model

from nerfart_plugin.config.issues import Issue, issues_from, suggest, unknown_key
from nerfart_plugin.config.types import Color, PathText, Setting


def _check(model: type[BaseModel], values: dict, prefix: str) -> tuple[dict, list[Issue]]:
    """Validate ``values`` against ``model``: (coerced values that were given, issues)."""
    try:
        return model.model_validate(values).model_dump(exclude_unset=True), []
    except ValidationError as exc:
        return values, issues_from(exc, model, values, prefix)


def _registered(kind: str, name: Any, key: str) -> tuple[Any, list[Issue]]:
    from nerfart_plugin.config import registry

    valid = registry.names(kind)
    if isinstance(name, str) and name in valid:
        return registry.get(kind, name), []
    return None, [Issue(key, name, "one of " + ", ".join(valid) + suggest(str(name), valid))]


def _mapping(section: str, value: Any) -> tuple[dict, list[Issue]]:
    if isinstance(value, dict):
        return value, []
    return {}, [Issue(section, value, "a section of settings (" + section + ".key=value)")]


@functools.lru_cache(maxsize=None)
def named_model(kind: str, name: str) -> type[BaseModel]:
    """The pydantic model of a component section (``encoding``, ``backbone``): ``name`` + the ``Config``
    declared beside the registered component."""
    from nerfart_plugin.config import registry
    from nerfart_plugin.config.components import config_of

    config = config_of(registry.get(kind, name))
    return create_model(f"{config.__qualname__.replace('.', '')}Section", __base__=config, name=(str, ...))


def check_encoding(cfg: Any, prefix: str = "encoding") -> tuple[dict, list[Issue]]:
    """``encoding`` (or a nested one such as ``backbone.dir_encoding``): ``name`` + the encoding's settings."""
    cfg, issues = _mapping(prefix, cfg)
    name = cfg.get("name")
    cls, issues2 = _registered("encoding", name, f"{prefix}.name")
    if cls is None:
        return cfg, issues + issues2
    return _check(named_model("encoding", name), cfg, prefix)


def check_backbone(cfg: Any) -> tuple[dict, list[Issue]]:
    """``backbone``: ``name`` + the field's settings (``dir_encoding`` checked as an encoding)."""
    cfg, issues = _mapping("backbone", cfg)
    cls, issues2 = _registered("backbone", cfg.get("name"), "backbone.name")
    if cls is None:
        return cfg, issues + issues2
    out, issues = _check(named_model("backbone", cfg["name"]), cfg, "backbone")
    if isinstance(cfg.get("dir_encoding"), dict):
        enc, more = check_encoding(cfg["dir_encoding"], "backbone.dir_encoding")
        out = {**out, "dir_encoding": enc}
        issues += more
    return out, issues


DataBackground = Optional[Union[Color, Literal["white", "black"]]]
#: the settings of ``data`` that the datamodule reads besides the loader's (one FieldInfo each: data_model caches)
DATA_EXTRAS: tuple[tuple[str, Any, Any], ...] = (
    ("kind", str, ...), ("path", Optional[PathText], None),
    ("ndc", Optional[bool], Setting(None, description="NDC rays; null: for forward-facing captures")),
    ("background_color", DataBackground, None),
    ("subject", Optional[Literal["person", "object", "scene"]],
     Setting(None, description="what the capture shows (source text of Eq. 4); stylization only: it reaches the "
             "stylization key through the source prompt", changes_results=False)),
)


@functools.lru_cache(maxsize=None)
def data_model(kind: str) -> type[BaseModel]:
    """The pydantic model of ``data`` for loader ``kind``: the loader's ``Config`` + :data:`DATA_EXTRAS`."""
    from nerfart_plugin.config import registry
    from nerfart_plugin.config.components import config_of

    config = config_of(registry.get("data", kind))
    return create_model(f"{config.__name__}Section", __base__=config,
                        **{name: (tp, default) for name, tp, default in DATA_EXTRAS})


def check_data(cfg: Any) -> tuple[dict, list[Issue]]:
    """``data``: ``kind`` + the loader's settings + the datamodule's (path, ndc, background_color, subject)."""
    cfg, issues = _mapping("data", cfg)
    loader, issues2 = _registered("data", cfg.get("kind"), "data.kind")
    if loader is None:
        return cfg, issues + issues2
    if cfg.get("path") == "???":
        return cfg, [Issue("data.path", "???", f"required for data={cfg['kind']}: set data.path=/path/to/scene")]
    return _check(data_model(cfg["kind"]), cfg, "data")


_GUIDANCE_KEYS = ("name", "allow_random_weights", "allow_download", "perceptual")


class GuidanceCommon(BaseModel):
    """The keys of ``guidance`` shared by every guidance; the sub-sections are checked per component."""

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)

    name: str = Setting("clip", description="the guidance: clip | imagenet | toy (the registry's guidance names)")
    allow_random_weights: bool = Setting(False, description="tests only: random CLIP/VGG weights (outputs stamped)")
    allow_download: Optional[bool] = Setting(None, description="fetch missing weights; null: env NERFART_ALLOW_DOWNLOAD")
    perceptual: Optional[str] = Setting(
        None, description="Eq. 9 features: vgg | edges | imagenet (the registry's perceptual networks); null: the "
        "guide's own (vgg for clip, edges for toy, imagenet for imagenet)")


def guidance_parts() -> dict[str, type[BaseModel]]:
    """Sub-section key of ``guidance`` -> the ``Config`` declared beside its guide or perceptual network
    (each Config's ``section`` names its key: ``guidance.clip``, ``guidance.vgg``, ``guidance.lite_perceptual``)."""
    from nerfart_plugin.config import registry
    from nerfart_plugin.config.components import config_of

    parts: dict[str, type[BaseModel]] = {}
    for kind in ("guidance", "perceptual"):
        for name in registry.names(kind):
            config = config_of(registry.get(kind, name))
            parts[config.key()] = config
    return parts


def check_guidance(cfg: Any) -> tuple[dict, list[Issue]]:
    """``guidance``: the common keys, then each sub-section (``clip``, ``vgg``, ...) by its component's Config."""
    cfg, issues = _mapping("guidance", cfg)
    _, issues2 = _registered("guidance", cfg.get("name"), "guidance.name")
    if issues2:
        return cfg, issues + issues2
    try:
        common = GuidanceCommon.model_validate(cfg).model_dump(exclude_unset=True)
    except ValidationError as exc:
        return cfg, issues_from(exc, GuidanceCommon, cfg, "guidance")
    if common.get("perceptual") is not None:
        issues += _registered("perceptual", common["perceptual"], "guidance.perceptual")[1]
    parts = guidance_parts()
    out = {k: common[k] for k in _GUIDANCE_KEYS if k in common}
    for key, value in cfg.items():
        if key in _GUIDANCE_KEYS:
            continue
        if key not in parts:
            valid = sorted([*_GUIDANCE_KEYS, *parts])
            issues.append(unknown_key(f"guidance.{key}", value, [f"guidance.{v}" for v in valid]))
            continue
        sub, more = _mapping(f"guidance.{key}", value)
        out[key], more2 = _check(parts[key], sub, f"guidance.{key}")
        issues += more + more2
    return out, issues


COMPONENTS: dict[str, Callable[[Any], tuple[dict, list[Issue]]]] = {
    "data": check_data, "backbone": check_backbone, "encoding": check_encoding, "guidance": check_guidance,
}
