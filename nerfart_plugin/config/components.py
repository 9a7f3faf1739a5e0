"""Typed configs of the pluggable components, declared beside each component.

A component built from config (a data loader, backbone, encoding, guide or perceptual network) carries its
``Config``: a pydantic model whose fields are the user's settings, each with its default, its valid range
and its meaning (:func:`~nerfart_plugin.config.types.Setting`). The schema composes these models to check a
run's config before any work (:mod:`nerfart_plugin.config.schema`), ``--help`` lists them, and the component reads
its settings from an instance. Unknown options are refused with the closest valid names, whether they come
from the command line or from a call in Python::

    class H3DSConfig(LoaderConfig):
        cameras_file: Optional[str] = Setting(None, description="which cameras npz to read")

    @register("data", "h3ds")
    @configured(H3DSConfig)
    def load_h3ds(path, cfg: H3DSConfig, context: LoaderContext) -> Scene: ...

    load_h3ds(folder, resolution=64)   # checked against H3DSConfig
"""

from __future__ import annotations

import functools
from typing import Any, Callable, ClassVar, Mapping, Optional, TypeVar, Union

from pydantic import BaseModel, ValidationError

from nerfart_plugin.config.issues import issues_from, raise_issues
from nerfart_plugin.config.types import SettingsModel

C = TypeVar("C", bound="ComponentConfig")


class ComponentConfig(SettingsModel, frozen=True):
    """The settings of one component; subclasses declare fields with :func:`~nerfart_plugin.config.types.Setting`."""

    #: where these settings live in a run's config (error messages name ``<section>.<key>``)
    section: ClassVar[str] = ""

    @classmethod
    def build(cls: type[C], cfg: Union[C, Mapping[str, Any], None] = None, **options: Any) -> C:
        """``cfg`` (an instance or a mapping; None: the defaults) with ``options`` on top, checked: a wrong value
        or an unknown option raises one :class:`~nerfart_plugin.errors.ConfigError` naming the valid ones."""
        if isinstance(cfg, cls) and not options:
            return cfg
        base = cfg.model_dump(exclude_unset=True) if isinstance(cfg, BaseModel) else dict(cfg or {})
        values = {**base, **options}
        try:
            return cls.model_validate(values)
        except ValidationError as exc:
            raise_issues(issues_from(exc, cls, values, cls.section))
            raise  # pragma: no cover - raise_issues raised


def configured(config: type[C]) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorate a function component ``fn(path, cfg, context)``: it is then called as ``fn(path, cfg=None,
    context=None, **options)`` (options checked by ``config.build``), and ``fn.Config`` is ``config``."""

    def wrap(fn: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(fn)
        def call(path: Any, cfg: Optional[Any] = None, context: Optional[Any] = None, **options: Any) -> Any:
            return fn(path, config.build(cfg, **options), context)

        call.Config = config  # type: ignore[attr-defined]
        return call

    return wrap


def config_of(component: Any) -> type[ComponentConfig]:
    """The ``Config`` a registered component declares."""
    config = getattr(component, "Config", None)
    if not (isinstance(config, type) and issubclass(config, ComponentConfig)):
        name = getattr(component, "__qualname__", repr(component))
        raise TypeError(f"{name} declares no Config (a ComponentConfig subclass beside it)")
    return config
