"""The viewer's Region panel: draw a box on the field, see the style inside it only, save it as a region file.

A transform gizmo (viser's transform controls) places and turns the box; three numbers size it; a wireframe shows
it over the field in every tab. "Style inside the box only" renders the stylization inside the box and the source
everywhere else (:meth:`nerfart_plugin.api.Run.with_region`), at the dial's strength; "Save region" writes
``<run>/regions/region-<hash>.npz`` (the command-line ``region=`` and :meth:`~nerfart_plugin.api.Region.load`
read it) and shows the shorthand that makes the same box on the command line. Everything is in the capture's world
frame, the frame of the page, of the exported meshes and of ``region.box``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional

import numpy as np

from nerfart_plugin.regions import Region
from nerfart_plugin.viewer.cameras import wxyz_to_matrix

log = logging.getLogger("nerfart_plugin")

#: the box a panel opens with: this share of the scene's scale on each half side
START_HALF = 0.25
BOX_COLOUR = (255, 160, 0)


def euler_degrees(R: np.ndarray) -> list[float]:
    """The XYZ Euler angles in degrees (x first, then y, then z; ``region.rotation``) of a rotation [3,3]."""
    sy = float(np.clip(-R[2, 0], -1.0, 1.0))
    y = np.arcsin(sy)
    if abs(np.cos(y)) > 1e-6:
        x, z = np.arctan2(R[2, 1], R[2, 2]), np.arctan2(R[1, 0], R[0, 0])
    else:  # gimbal lock: all of the rotation about x
        x, z = np.arctan2(-R[1, 2], R[1, 1]), 0.0
    return [round(float(np.degrees(a)), 3) for a in (x, y, z)]


class RegionPanel:
    """The box, its gizmo and the panel's controls (see the module docstring).

    Args:
        viewer: the running :class:`~nerfart_plugin.viewer.server.Viewer`; folder: the run folder (``regions/`` is
            written there).
    """

    def __init__(self, viewer: Any, folder: Path) -> None:
        self.viewer, self.folder = viewer, Path(folder)
        gui, scale = viewer.server.gui, float(viewer.scale)
        half = START_HALF * scale
        with gui.add_folder("Region"):
            self.show = gui.add_checkbox("Show the region box", initial_value=False,
                                         hint="a box on the field: drag the gizmo to place and turn it")
            self.half = gui.add_vector3("Half sizes", initial_value=(half, half, half), min=(1e-4,) * 3,
                                        step=0.01 * scale, hint="world units, along the box's own axes")
            self.feather = gui.add_number("Feather", initial_value=0.02 * scale, min=0.0, step=0.005 * scale,
                                          hint="width of the soft edge, outward (world units)")
            self.inside = gui.add_checkbox("Style inside the box only", initial_value=False,
                                           hint="the source outside the box, no retraining")
            self.save_button = gui.add_button("Save region", hint="writes <run>/regions/region-<hash>.npz")
            self.note = gui.add_markdown("")
        self.gizmo = viewer.server.scene.add_transform_controls("/region", scale=0.6 * scale,
                                                                position=tuple(viewer.centre), visible=False)
        self.box = viewer.server.scene.add_box("/region/box", color=BOX_COLOUR, dimensions=(2 * half,) * 3,
                                               wireframe=True, visible=False)
        self.show.on_update(lambda _: self._visibility())
        self.half.on_update(lambda _: self._changed())
        self.feather.on_update(lambda _: self._changed())
        self.gizmo.on_update(lambda _: self._changed())
        self.inside.on_update(lambda _: self._changed())
        self.save_button.on_click(lambda _: self.save())

    def region(self) -> Region:
        """The box as a :class:`~nerfart_plugin.api.Region` (world units)."""
        return Region.box(np.asarray(self.gizmo.position, dtype=np.float64), np.asarray(self.half.value, dtype=np.float64),
                          rotation=wxyz_to_matrix(np.asarray(self.gizmo.wxyz)), feather=float(self.feather.value))

    def shorthand(self) -> str:
        """The command-line settings that make the same box."""
        c = [round(float(v), 4) for v in self.gizmo.position]
        h = [round(float(v), 4) for v in self.half.value]
        R = wxyz_to_matrix(np.asarray(self.gizmo.wxyz))
        return (f"region.box=[{','.join(map(str, c + h))}] region.rotation=[{','.join(map(str, euler_degrees(R)))}] "
                f"region.feather={round(float(self.feather.value), 4)}")

    def _visibility(self) -> None:
        self.gizmo.visible = self.box.visible = bool(self.show.value)

    def _changed(self) -> None:
        self.box.dimensions = tuple(2.0 * float(v) for v in self.half.value)
        self.note.content = f"`{self.shorthand()}`"
        self.viewer.update(region=self.region() if self.inside.value else None)

    def save(self) -> Optional[Path]:
        """Write the box as ``<run>/regions/region-<hash>.npz``; the panel says where and the shorthand."""
        region = self.region()
        path = region.save(self.folder / "regions" / f"region-{region.content_hash[:8]}.npz")
        self.note.content = f"saved `{path}`\n\n`region={path}` or `{self.shorthand()}`"
        log.info("region saved: %s", path)
        return path
