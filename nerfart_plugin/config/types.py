"""Typed setting annotations shared by the config schema and the components' ``Config`` models.

A component built from config (a backbone, encoding, data loader, guide) states the type, valid range
and meaning of each setting in the ``Config`` beside it (:mod:`nerfart_plugin.config.components`)::

    class Config(NeuralField.Config):
        hidden_dim: Width = Setting(64, description="width of the geometry net")

:mod:`nerfart_plugin.config.schema` composes them to check a config before any work.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal, Optional, Union

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field
from pydantic.fields import FieldInfo

__all__ = [
    "SettingsModel", "Color", "PathText", "Setting", "changes_results", "Limits", "Int", "Float", "Width", "Depth", "Fraction", "PositiveFloat", "Resolution", "Seed",
    "HoldoutEvery", "MAX_WIDTH", "MAX_DEPTH",
]

class SettingsModel(BaseModel):
    """The one base of every settings model (the run's sections and the components' Configs): unknown keys
    refused, numbers finite, fields named freely (``model``, ``model_overrides``)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, arbitrary_types_allowed=True,
                              protected_namespaces=())


#: constraints inside ``Annotated[...]`` (pydantic's ``Field``, named apart from the project's field classes)
Limits = Field

MAX_WIDTH = 2048  # MLP width / feature size: 16 layers x 2048^2 is ~270 MB of float32 weights
MAX_DEPTH = 16


def _no_bool(value: Any) -> Any:
    """Numbers only: ``true``/``false`` is not a count or a rate (pydantic would read it as 1/0)."""
    if isinstance(value, bool):
        raise ValueError("a number is expected, not a boolean")
    return value


def Setting(default: Any = ..., *, description: Optional[str] = None, off: Optional[str] = None,
            allowed: Optional[str] = None, changes_results: bool = True, **constraints: Any) -> Any:
    """A pydantic ``Field`` with ``off``: how to say "off" when a user gives 0 / null for a setting
    that does not accept it, ``allowed``: what the error message says is allowed (default:
    derived from the type and constraints), and ``changes_results=False`` for a setting that does
    not change what a run computes (how often it logs or saves, how much it renders at once): it is
    left out of the cache keys of the run folders (:func:`result_settings`)."""
    extra: dict[str, Any] = {k: v for k, v in (("off", off), ("allowed", allowed)) if v}
    if not changes_results:
        extra["changes_results"] = False
    if default is ...:
        return Field(description=description, json_schema_extra=extra or None, **constraints)
    return Field(default, description=description, json_schema_extra=extra or None, **constraints)


def changes_results(info: FieldInfo) -> bool:
    """False for a field made by :func:`Setting` with ``changes_results=False``."""
    extra = info.json_schema_extra
    return not (isinstance(extra, dict) and extra.get("changes_results") is False)


def off_hint(info: FieldInfo) -> Optional[str]:
    """The ``off`` text of a field made by :func:`Setting` (None if it has none)."""
    extra = info.json_schema_extra
    return extra.get("off") if isinstance(extra, dict) else None  # type: ignore[return-value]


def allowed_text(info: FieldInfo) -> Optional[str]:
    """The ``allowed`` text of a field made by :func:`Setting` (None: derive it from the type)."""
    extra = info.json_schema_extra
    return extra.get("allowed") if isinstance(extra, dict) else None  # type: ignore[return-value]


#: an integer that is not a boolean
Int = Annotated[int, BeforeValidator(_no_bool)]
#: a finite number that is not a boolean
Float = Annotated[float, BeforeValidator(_no_bool)]
#: width of an MLP layer or size of a feature vector
Width = Annotated[Int, Field(ge=1, le=MAX_WIDTH)]
#: number of hidden layers of an MLP (0: a single linear layer)
Depth = Annotated[Int, Field(ge=0, le=MAX_DEPTH)]
#: a fraction in (0, 1]
Fraction = Annotated[Float, Field(gt=0.0, le=1.0)]
#: a number > 0
PositiveFloat = Annotated[Float, Field(gt=0.0)]
#: long image side in pixels ("auto": min(native, 480); null: native size)
Resolution = Optional[Union[Literal["auto"], Annotated[Int, Field(ge=8, le=8192)]]]
#: a random seed (numpy and Lightning accept unsigned 32-bit seeds)
Seed = Annotated[Int, Field(ge=0, le=2**32 - 1)]
#: every n-th view is held out for validation; 0: none (all views train)
HoldoutEvery = Annotated[Int, Field(ge=0, le=10_000)]

#: an RGB colour, each channel in [0, 1]
Color = Annotated[list[Annotated[Float, Field(ge=0.0, le=1.0)]], Field(min_length=3, max_length=3)]
#: a file or folder path as typed
PathText = Union[str, Path]
