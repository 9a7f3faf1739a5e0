"""Config violations as the user reads them: one :class:`Issue` per bad key (``key=value: what is allowed (how
to turn it off)``), built from pydantic's errors with the closest valid key for a typo, and raised as ONE
:class:`~nerfart_plugin.errors.ConfigError` listing them all."""

from __future__ import annotations

import collections.abc
import difflib
import math
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Optional, Union

import annotated_types as at
from pydantic import BaseModel, ValidationError
from pydantic.fields import FieldInfo

from nerfart_plugin.config.types import allowed_text, off_hint
from nerfart_plugin.errors import ConfigError


@dataclass
class Issue:
    """One violation: ``key=value: allowed (off)``."""

    key: str
    value: Any
    allowed: str
    off: Optional[str] = None

    def __str__(self) -> str:
        text = f"{self.key}={show(self.value)}: {self.allowed}"
        return f"{text} ({self.off})" if self.off and _zero_like(self.value) else text


def show(value: Any) -> str:
    """A value as a user would type it on the command line."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(show(v) for v in value) + "]"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, (int, Path)):
        return str(value)
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _zero_like(value: Any) -> bool:
    """0, null, false, empty: the values a user types to mean "off"."""
    if value is None or value is False or (isinstance(value, (list, tuple, dict)) and not value):
        return True
    if isinstance(value, (int, float)):
        return value == 0 or (isinstance(value, float) and math.isnan(value))
    return isinstance(value, str) and value.strip().lower() in ("", "0", "none", "null", "off", "false", "no")


def raise_issues(issues: list[Issue]) -> None:
    """Raise one ConfigError listing every issue (nothing if there is none)."""
    if not issues:
        return
    seen: dict[str, Issue] = {}
    for issue in issues:
        seen.setdefault(issue.key, issue)
    lines = [str(i) for i in seen.values()]
    if len(lines) == 1:
        raise ConfigError(lines[0])
    raise ConfigError(f"{len(lines)} invalid settings:\n  " + "\n  ".join(lines))


def _number(x: Any) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _bounds(meta: list[Any]) -> str:
    """' in [1, 4096]', ' > 0', ... from annotated_types constraints."""
    lo = hi = None
    for m in meta:
        if isinstance(m, at.Ge):
            lo = f"[{_number(m.ge)}"
        elif isinstance(m, at.Gt):
            lo = f"({_number(m.gt)}"
        elif isinstance(m, at.Le):
            hi = f"{_number(m.le)}]"
        elif isinstance(m, at.Lt):
            hi = f"{_number(m.lt)})"
    if lo and hi:
        return f" in {lo}, {hi}"
    if lo:
        return (" >= " if lo[0] == "[" else " > ") + lo[1:]
    if hi:
        return (" <= " if hi[-1] == "]" else " < ") + hi[:-1]
    return ""


def _flat_meta(meta: list[Any]) -> list[Any]:
    out: list[Any] = []
    for m in meta:
        out.extend(m.metadata if isinstance(m, FieldInfo) else [m])
    return out


def _choice(value: Any) -> str:
    """A choice as typed on the command line (text unquoted)."""
    return value if isinstance(value, str) else show(value)


def _choices(tp: Any) -> Optional[list[Any]]:
    """The values a Literal / bool allows (None for other types)."""
    if typing.get_origin(tp) is Literal:
        return list(typing.get_args(tp))
    return [True, False] if tp is bool else None


def describe(tp: Any, meta: Optional[list[Any]] = None) -> str:
    """What a type annotation (with its constraints) allows, in words."""
    meta = _flat_meta(list(meta or []))
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Annotated:
        return describe(args[0], [*args[1:], *meta])
    if origin in (Union, types.UnionType):
        rest = [a for a in args if a is not type(None)]
        values = [v for a in rest for v in (_choices(a) or [])]
        others = [describe(a, meta if len(rest) == 1 else None) for a in rest if _choices(a) is None]
        choice = "true or false" if values == [True, False] else "one of " + ", ".join(_choice(v) for v in values)
        parts = ([choice] if values else []) + others
        return ", or ".join(parts) + (", or null" if len(rest) < len(args) else "")
    choices = _choices(tp)
    if choices is not None:
        return "true or false" if tp is bool else "one of " + ", ".join(_choice(a) for a in choices)
    if tp is int:
        return "an integer" + _bounds(meta)
    if tp is float:
        return "a number" + _bounds(meta)
    if tp is str:
        return "non-empty text" if _min_len(meta) else "text"
    if tp is Path:
        return "a path"
    if origin in (list, tuple, collections.abc.Sequence) or tp in (list, tuple):
        n_lo, n_hi = _min_len(meta), _max_len(meta)
        size = f"{n_lo} values" if n_lo is not None and n_lo == n_hi else "at least one value" if n_lo else "values"
        return f"a list of {size}" + (f", each {describe(args[0])}" if args else "")
    if origin in (dict, collections.abc.Mapping) or tp is dict:
        return "a mapping of settings"
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return "a section of settings"
    if tp is Any:
        return "any value"
    return f"a {getattr(tp, '__name__', str(tp))}"


def _min_len(meta: list[Any]) -> Optional[int]:
    return next((m.min_length for m in meta if isinstance(m, at.MinLen)), None)


def _max_len(meta: list[Any]) -> Optional[int]:
    return next((m.max_length for m in meta if isinstance(m, at.MaxLen)), None)


def _model_in(tp: Any) -> Optional[type[BaseModel]]:
    """The BaseModel subclass an annotation is (or is optionally), else None."""
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return tp
    if typing.get_origin(tp) in (Union, types.UnionType, Annotated):
        for a in typing.get_args(tp):
            m = _model_in(a)
            if m is not None:
                return m
    return None


def suggest(key: str, valid: list[str]) -> str:
    """'; did you mean x?' for the closest valid key, or ''."""
    close = difflib.get_close_matches(key, valid, n=1, cutoff=0.6)
    return f"; did you mean {close[0]}?" if close else ""


def unknown_key(key: str, value: Any, valid: list[str]) -> Issue:
    """An Issue for a key that no section or component accepts, with the closest valid one
    (``valid``: dotted keys of the same section; names are compared without the section prefix)."""
    prefix, _, name = key.rpartition(".")
    lead = f"{prefix}." if prefix else ""
    names = [v[len(lead):] if v.startswith(lead) else v for v in valid]
    close = difflib.get_close_matches(name, names, n=1, cutoff=0.6)
    hint = f"; did you mean {lead}{close[0]}?" if close else ""
    return Issue(key, value, f"unknown setting{hint} (valid: {', '.join(valid)})")


def issues_from(exc: ValidationError, model: type[BaseModel], data: Any, prefix: str = "") -> list[Issue]:
    """One Issue per invalid key of a pydantic ValidationError (union branches and list items merged)."""
    out: list[Issue] = []
    for err in exc.errors():
        cls: Optional[type[BaseModel]] = model
        info: Optional[FieldInfo] = None
        path: list[str] = []
        value = data
        loc = list(err["loc"])
        for part in loc:
            if isinstance(part, str) and cls is not None and part in cls.model_fields:
                info = cls.model_fields[part]
                path.append(part)
                value = value.get(part) if isinstance(value, dict) else None
                cls = _model_in(info.annotation)
            else:
                break
        dotted = ".".join([p for p in (prefix,) if p] + path)
        if err["type"] == "extra_forbidden":
            extra = str(loc[len(path)])
            parent = dotted
            key = f"{parent}.{extra}" if parent else extra
            valid = sorted(cls.model_fields) if cls is not None else []
            where = f"{parent}." if parent else ""
            out.append(unknown_key(key, err["input"], [f"{where}{v}" for v in valid]))
        elif info is not None:
            out.append(Issue(dotted, value, allowed_text(info) or describe(info.annotation, info.metadata),
                             off_hint(info)))
        else:
            out.append(Issue(dotted or "(config)", value, err["msg"]))
    return out
