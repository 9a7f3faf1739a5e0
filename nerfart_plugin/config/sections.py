"""The component sections of a run's config: one idiom for every family of pluggable components.

A family (``data``, ``backbone``, ``encoding``, ``guidance`` and the guide's ``guidance.perceptual``, the
backbone's ``backbone.dir_encoding``) is a section whose ``name`` picks a registered component; its other keys
are the settings the component declares in its ``Config`` (:mod:`nerfart_plugin.config.components`), plus the
few the run itself reads for that family (:data:`EXTRAS`: the data's ``path``, the guide's weights policy). The
section is typed as that component's Config: a discriminated union on ``name`` whose members come from the
registry, so a third-party component is checked and typed like a shipped one::

    data: {name: h3ds, path: null, resolution: auto, ...}          -> H3DSConfig + path, ndc, background_color, subject
    guidance: {name: clip, model: ViT-B-32, ..., perceptual: {name: vgg, weights: DEFAULT, ...}}

:func:`check_section` checks a section as the user gave it (every bad key one :class:`Issue`, with the closest
valid key, and the keys that moved named with their new place); :func:`typed_section` gives the typed model.
"""

from __future__ import annotations

import functools
from typing import Any, Literal, Optional, Union

from omegaconf import DictConfig, OmegaConf
from pydantic import BaseModel, ValidationError, create_model

from nerfart_plugin.config import registry
from nerfart_plugin.config.components import ComponentConfig, config_of
from nerfart_plugin.config.issues import Issue, issues_from, raise_issues, suggest
from nerfart_plugin.config.types import Color, PathText, Setting

#: section key -> the registry kind its ``name`` picks
FAMILIES: dict[str, str] = {
    "data": "data", "backbone": "backbone", "encoding": "encoding", "guidance": "guidance",
    "guidance.perceptual": "perceptual", "backbone.dir_encoding": "encoding",
}
#: nested families held as typed sections in their parent (the others, ``backbone.dir_encoding``, stay mappings the
#: component reads itself, checked the same way)
TYPED_NESTED = ("guidance.perceptual",)
#: the families that are top-level sections of a run's config
TOP_LEVEL = ("data", "backbone", "encoding", "guidance")

DataBackground = Optional[Union[Color, Literal["white", "black"]]]

#: registry kind -> the settings a run reads besides the component's own: ``(name, type, default)``
EXTRAS: dict[str, tuple[tuple[str, Any, Any], ...]] = {
    "data": (
        ("path", Optional[PathText], Setting(None, description="the capture (a folder, or a video for selfie)")),
        ("ndc", Optional[bool], Setting(None, description="NDC rays; null: for forward-facing captures")),
        ("background_color", DataBackground, Setting(None, description="the photos' background behind a mask")),
        ("subject", Optional[Literal["person", "object", "scene"]],
         Setting(None, description="what the capture shows (source text of Eq. 4); stylization only: it reaches "
                 "the stylization key through the source prompt", changes_results=False)),
    ),
    "guidance": (
        ("allow_random_weights", bool, Setting(False, description="tests only: random CLIP/VGG weights (outputs "
                                               "stamped)")),
        ("allow_download", Optional[bool], Setting(None, description="fetch missing weights; null: env "
                                                   "NERFART_ALLOW_DOWNLOAD")),
        ("perceptual", Optional[ComponentConfig], Setting(None, description="Eq. 9 features: "
                                                          "{name: vgg | edges | imagenet, ...its settings}; null: "
                                                          "the guide's own (vgg for clip, edges for toy, imagenet for "
                                                          "imagenet)")),
    ),
}

#: where the settings of a guide or perceptual network lived before they moved into their family's section
MOVED_GUIDANCE_KEYS = ("clip", "vgg", "imagenet", "lite_perceptual", "toy", "edges")


class ComponentSection(ComponentConfig):
    """What every component section has: the registered ``name`` of its component."""

    name: str = Setting(..., description="the registered component")


@functools.lru_cache(maxsize=None)
def section_model(kind: str, name: str) -> type[ComponentConfig]:
    """The typed section of component ``name`` of registry ``kind``: its ``Config``, ``name`` and the run's
    :data:`EXTRAS` for the kind (cached: one class per component)."""
    config = config_of(registry.get(kind, name))
    fields = {"name": (Literal[name], Setting(name, description=f"the {kind} component"))}
    fields.update({key: (tp, default) for key, tp, default in EXTRAS.get(kind, ())})
    return create_model(f"{config.__qualname__.replace('.', '')}Section", __base__=(config,), **fields)


def _mapping(key: str, value: Any) -> tuple[dict, list[Issue]]:
    if isinstance(value, BaseModel):
        return value.model_dump(exclude_unset=True), []
    if isinstance(value, DictConfig):
        value = OmegaConf.to_container(value, resolve=True)
    if isinstance(value, dict):
        return value, []
    return {}, [Issue(key, value, f"a section of settings ({key}.name=... and its settings)")]


def _moved(key: str, values: dict) -> list[Issue]:
    """The keys of the settings layout before one idiom (``data.kind``, ``guidance.clip.*``), named with their new
    place."""
    issues = []
    if key == "data" and "kind" in values:
        issues.append(Issue("data.kind", values["kind"], "the loader is chosen by data.name now: "
                            f"data.name={values['kind']} (or the group: data={values['kind']})"))
    if key == "guidance":
        for old in MOVED_GUIDANCE_KEYS:
            if isinstance(values.get(old), dict):
                issues.append(Issue(f"guidance.{old}", values[old], "these settings moved: the guide's are "
                                    "guidance.<key> (guidance.pretrained=...), the perceptual network's "
                                    "guidance.perceptual.<key> (guidance.perceptual.weights=...)"))
    return issues


def check_section(key: str, value: Any) -> tuple[dict, list[Issue]]:
    """Check the component section ``key`` (a :data:`FAMILIES` key) as given: ``(its values coerced where
    validation changed their meaning, the issues)``. Only the keys given are returned (defaults are the
    component's), so the result is what a run folder's ``config.yaml`` records."""
    kind = FAMILIES[key]
    if isinstance(value, str) and key in ("guidance.perceptual", "backbone.dir_encoding"):
        value = {"name": value}  # guidance.perceptual=imagenet: that network with its defaults
    values, issues = _mapping(key, value)
    if issues:
        return values, issues
    moved = _moved(key, values)
    if moved:
        return values, moved
    name = values.get("name")
    valid = registry.names(kind)
    if not (isinstance(name, str) and name in valid):
        return values, [Issue(f"{key}.name", name, "one of " + ", ".join(valid) + suggest(str(name), valid))]
    if key == "data" and values.get("path") == "???":
        return values, [Issue("data.path", "???", f"required for data={name}: set data.path=/path/to/scene")]
    nested = {k: v for k, v in values.items() if f"{key}.{k}" in FAMILIES and v is not None}
    flat = {k: v for k, v in values.items() if k not in nested}
    model = section_model(kind, name)
    try:
        out = model.model_validate(flat).model_dump(exclude_unset=True)
    except ValidationError as exc:
        out, issues = flat, issues_from(exc, model, flat, key)
    for sub, sub_value in nested.items():
        out[sub], more = check_section(f"{key}.{sub}", sub_value)
        issues += more
    return out, issues


def typed_section(key: str, value: Any) -> ComponentConfig:
    """The component section ``key`` as its typed model (an instance of the component's ``Config``, so the
    component reads it as its own); a model of the family as it is. Raises one ConfigError naming every bad
    key (``<key>.<setting>``)."""
    if isinstance(value, ComponentSection) or (isinstance(value, ComponentConfig) and hasattr(value, "name")):
        return value
    values, issues = check_section(key, value)
    raise_issues(issues)
    kind = FAMILIES[key]
    nested = {k: typed_section(f"{key}.{k}", v) for k, v in values.items() if f"{key}.{k}" in TYPED_NESTED
              and v is not None}
    model = section_model(kind, values["name"])
    return model.model_validate({**{k: v for k, v in values.items() if k not in nested}, **nested})


def given(section: Any) -> dict[str, Any]:
    """The settings a typed section was given (nested sections as dicts): plain data for records."""
    if not isinstance(section, BaseModel):
        return dict(section)
    out = {}
    for k in section.model_fields_set:
        v = getattr(section, k)
        out[k] = given(v) if isinstance(v, BaseModel) else v
    return out


def section_keys(key: str, name: str) -> list[str]:
    """The settings of component section ``key`` when its ``name`` is ``name`` (dotted, for messages and docs)."""
    return [f"{key}.{k}" for k in section_model(FAMILIES[key], name).model_fields]
