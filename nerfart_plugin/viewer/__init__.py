"""A live web viewer of radiance fields (viser): fly through a finished run, dial the style, lay a camera path,
or watch a run train.

    python -m nerfart_plugin.viewer outputs/stylizations/<run>          # serves http://127.0.0.1:8080
    python -m nerfart_plugin guidance=imagenet +prompt=Joker viewer.live=true   # watch the training

The page opens on the capture's front camera and renders the field from the browser's camera: a fast
low-resolution frame while the camera moves, refined once it rests (:mod:`~nerfart_plugin.viewer.schedule`).
Panels: the channel, source | stylized | split, the strength dial and the mix weights of other
stylizations of the same source, a region box to style inside only and save
(:mod:`~nerfart_plugin.viewer.region_panel`), the capture's cameras (click one to jump there), the run's mesh,
the run's facts, and the camera-path editor (:mod:`~nerfart_plugin.viewer.path_editor`). Each browser tab keeps
its own camera. The viewer binds 127.0.0.1 unless told otherwise and only reads the run folder (the path
editor writes under ``<run>/render``, the region panel under ``<run>/regions``).
"""

from __future__ import annotations

from typing import Any

__all__ = ["open_viewer"]


def __getattr__(name: str) -> Any:
    """``open_viewer`` loads the training stack (torch, the run's field, viser) when first asked for, so that
    ``python -m nerfart_plugin.viewer`` answers a bad argument before loading it."""
    if name == "open_viewer":
        from nerfart_plugin.viewer.app import open_viewer

        return open_viewer
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
