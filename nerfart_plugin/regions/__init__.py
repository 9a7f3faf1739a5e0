"""Regions of a scene: soft masks in the world frame (boxes, ellipsoids, grids lifted from 2D masks and their set
operations, :mod:`.region`), bound to a run's field as the masks of a
:class:`~nerfart_plugin.fields.composite.CompositeField` (stylize, render and export only a part)."""

from nerfart_plugin.regions.region import Region

__all__ = ["Region"]
