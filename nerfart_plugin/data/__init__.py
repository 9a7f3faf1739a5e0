"""Data: scene loaders (registry kind ``data``), rays, camera paths, the datamodule.

``load_scene(kind, path, **opts)`` dispatches to the loader registered as
``kind`` ("h3ds", "llff", "selfie", "nerfstudio") and returns a validated :class:`Scene`.
"""

from __future__ import annotations

from typing import Any

from nerfart_plugin.config import registry
from nerfart_plugin.data import h3ds, llff, nerfstudio, selfie  # noqa: F401  (register loaders)
from nerfart_plugin.data.rays import ndc_rays, pixel_rays, rays_for_views
from nerfart_plugin.data.scene import Scene


def load_scene(kind: str, path: Any, cfg: Any = None, context: Any = None, **options: Any) -> Scene:
    """Load a scene with the loader registered as ``data``/``kind``.

    ``cfg``: the loader's typed settings (its ``Config``, or a mapping), ``options`` on top of them, checked
    (an unknown option is a ConfigError naming the valid ones); ``context``: a
    :class:`~nerfart_plugin.data.loader.LoaderContext` (background, cache folder). Every loader takes
    ``resolution`` (long image side in pixels; antialiased resize, K scaled exactly), ``holdout_every``
    (default 8: ``val_ids = ids[::8]``) and ``use_masks`` (default True); see each loader's ``Config``.
    """
    return registry.get("data", kind)(path, cfg, context, **options)


__all__ = ["Scene", "load_scene", "pixel_rays", "ndc_rays", "rays_for_views"]


def __getattr__(name: str):  # the datamodule reads load_scene from this package: re-exported on first use
    if name in ("SceneDataModule", "default_scene_path"):
        from nerfart_plugin.data import datamodule

        return getattr(datamodule, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
