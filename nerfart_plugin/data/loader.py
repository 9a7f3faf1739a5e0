"""What every scene loader takes: its typed settings (:class:`LoaderConfig`, extended by each loader beside
it) and what the datamodule hands every loader alike (:class:`LoaderContext`).

A loader is ``fn(path, cfg, context) -> Scene`` registered as ``data``/``<kind>`` and decorated with
:func:`~nerfart_plugin.config.components.configured`, so that ``fn(path, resolution=64)`` also works and an
unknown option is refused with the closest valid names.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from nerfart_plugin.config.components import ComponentConfig
from nerfart_plugin.config.types import HoldoutEvery, Resolution, Setting


class LoaderConfig(ComponentConfig):
    """The settings every loader has (``data.<key>``)."""

    section = "data"

    resolution: Resolution = Setting(
        "auto", description="long image side in pixels (antialiased resize, intrinsics scaled exactly); auto: "
        "min(native, 480); null: native")
    holdout_every: HoldoutEvery = Setting(8, description="every n-th view is held out for evaluation (0: none)")
    use_masks: bool = Setting(True, description="load the capture's masks (mattes, alpha) when it has them")


@dataclass(frozen=True)
class LoaderContext:
    """What the datamodule gives every loader besides its settings (each uses what it needs).

    Attributes:
        background: the colour [3] in [0, 1] RGBA images are composited on (``data.background_color``); None: white.
        cache_root: the project's cache folder (frames and SfM of videos); None: the loader's default.
    """

    background: Optional[tuple[float, float, float]] = (1.0, 1.0, 1.0)
    cache_root: Optional[Path] = None
