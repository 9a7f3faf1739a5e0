"""The viewer's panels (viser GUI): view, style (strength and mix), capture cameras, mesh, run facts.

Each ``add_*`` function builds one panel on a :class:`~nerfart_plugin.viewer.server.Viewer` and wires it to
the viewer's shared settings; the camera-path editor is in :mod:`nerfart_plugin.viewer.path_editor` and
the training controls in :mod:`nerfart_plugin.viewer.live`.
"""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
from PIL import Image

from nerfart_plugin.results.blend import STRENGTH_RANGE, WEIGHT_RANGE
from nerfart_plugin.viewer.cameras import capture_camera, to_viser
from nerfart_plugin.viewer.sources import VIEW_CHANNELS, VIEW_MODES

log = logging.getLogger(__name__)

#: long side (pixels) of the photos shown on the capture's frustums
THUMBNAIL_SIDE = 96


def add_view_panel(viewer: Any, stylization: bool) -> dict[str, Any]:
    """Channel (rgb | depth | normal | opacity) and, for a stylization, what is shown (stylized | source |
    split: source left, stylized right)."""
    gui = viewer.server.gui
    handles: dict[str, Any] = {}
    with gui.add_folder("View"):
        handles["channel"] = gui.add_dropdown("Channel", VIEW_CHANNELS, initial_value="rgb",
                                              hint="what each pixel shows: colour, depth, surface normal, opacity")
        handles["channel"].on_update(lambda _: viewer.update(channel=handles["channel"].value))
        if stylization:
            handles["mode"] = gui.add_dropdown("Show", VIEW_MODES, initial_value="stylized",
                                               hint="split: the source on the left, the stylization on the right")
            handles["mode"].on_update(lambda _: viewer.update(mode=handles["mode"].value))
    return handles


def add_style_panel(viewer: Any, siblings: Sequence[Path]) -> dict[str, Any]:
    """The strength dial of this stylization and one weight per other stylization of the same source (the
    mix, :func:`nerfart_plugin.api.mix`); moving any of them renders the blend, no retraining."""
    gui = viewer.server.gui
    lo, hi = STRENGTH_RANGE
    wlo, whi = WEIGHT_RANGE
    sliders = []
    with gui.add_folder("Style"):
        sliders.append(gui.add_slider("Strength", min=lo, max=hi, step=0.05, initial_value=1.0,
                                      marks=((0.0, "source"), (1.0, "run"), (2.0, "2x")),
                                      hint="0: the source, 1: the run as trained, up to 2: past it"))
        for folder in siblings:
            sliders.append(gui.add_slider(f"Mix: {_run_label(folder)}", min=wlo, max=whi, step=0.05,
                                          initial_value=0.0, hint=f"weight of {folder.name} (0: left out)"))

    def changed(_: Any) -> None:
        viewer.update(weights=tuple(float(s.value) for s in sliders))

    for s in sliders:
        s.on_update(changed)
    return {"sliders": sliders}


def _run_label(folder: Path) -> str:
    try:
        return str(json.loads((folder / "metrics.json").read_text()).get("prompt") or folder.name)
    except (OSError, ValueError):
        return folder.name


class CaptureFrustums:
    """The capture's cameras as frustums in every tab (with their photos once read), shown or hidden by one
    checkbox. A click on a frustum moves that tab's camera there; the frustum of the camera a tab sits at
    is hidden in that tab (it would cover the view), as is the front camera's when a tab opens."""

    def __init__(self, viewer: Any) -> None:
        self.viewer = viewer
        self.photos: Optional[list[np.ndarray]] = None
        self.tabs: dict[int, list[Any]] = {}
        self.at: dict[int, int] = {}  # tab -> the camera it sits at (its frustum hidden)
        self.views = [capture_camera(viewer.cams, i) for i in range(len(viewer.cams.c2w))]
        self.show = viewer.server.gui.add_checkbox("Capture cameras", initial_value=True,
                                                   hint="the capture's views (blue: training, orange: held out); "
                                                        "click one to look through it")
        self.show.on_update(lambda _: self._visibility())
        viewer.tab_hooks.append(self.add_to)
        viewer.close_hooks.append(self.forget)
        viewer.panels["capture"] = self

    def add_to(self, client: Any) -> None:
        train = set(self.viewer.cams.train_ids)
        handles = []
        for i, cam in enumerate(self.views):
            wxyz, position = to_viser(cam)
            h = client.scene.add_camera_frustum(
                f"/capture/view_{i:03d}", fov=cam.fov_y, aspect=cam.aspect, scale=0.04 * self.viewer.scale,
                thickness=0.003 * self.viewer.scale, wxyz=wxyz, position=position,
                color=(40, 110, 220) if i in train else (220, 120, 40),
                image=None if self.photos is None else self.photos[i], format="jpeg")
            h.on_click(lambda event, i=i: self.jump(event.client, i))
            handles.append(h)
        self.tabs[client.client_id] = handles
        self.at[client.client_id] = self.viewer.front_index
        self._visibility()

    def jump(self, client: Any, i: int) -> None:
        self.at[client.client_id] = i
        self._visibility()
        self.viewer.jump(client, self.views[i])

    def _visibility(self) -> None:
        for tab, handles in list(self.tabs.items()):
            for i, h in enumerate(handles):
                h.visible = bool(self.show.value) and i != self.at.get(tab)

    def set_photos(self, photos: list[np.ndarray]) -> None:
        self.photos = photos
        for handles in list(self.tabs.values()):
            for h, img in zip(handles, photos):
                h.image = img

    def forget(self, client_id: int) -> None:
        self.tabs.pop(client_id, None)
        self.at.pop(client_id, None)


def load_photos_later(run: Any, layer: CaptureFrustums) -> threading.Thread:
    """Read the capture's photos in the background (from the run's data settings) and put them on the
    frustums; a capture whose data is not on this machine keeps bare frustums."""

    def work() -> None:
        try:
            scene = run.scene()
        except Exception as exc:  # noqa: BLE001 - the data may be elsewhere; the viewer works without photos
            log.info("viewer: the capture's photos are not available (%s); frustums without photos", exc)
            return
        layer.set_photos(thumbnails(scene.images.numpy()))

    t = threading.Thread(target=work, name="viewer-photos", daemon=True)
    t.start()
    return t


def thumbnails(images: np.ndarray, side: int = THUMBNAIL_SIDE) -> list[np.ndarray]:
    """[N,H,W,3] float images in [0,1] -> uint8 thumbnails with the long side at ``side`` pixels."""

    out = []
    for img in images:
        h, w = img.shape[:2]
        s = side / max(h, w)
        pil = Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
        out.append(np.asarray(pil.resize((max(1, round(w * s)), max(1, round(h * s))))))
    return out


def add_mesh_toggle(viewer: Any, mesh_file: Optional[Path]) -> Optional[Any]:
    """A checkbox that shows the run's extracted mesh (``mesh/`` of the run; loaded when first shown)."""
    if mesh_file is None:
        return None
    gui = viewer.server.gui
    box = gui.add_checkbox("Show mesh", initial_value=False, hint=f"{mesh_file.name}, over the field")
    state: dict[str, Any] = {}

    def toggle(_: Any) -> None:
        if box.value and "handle" not in state:
            import trimesh

            mesh = trimesh.load(mesh_file, force="mesh", process=False)
            state["handle"] = viewer.server.scene.add_mesh_trimesh("/mesh", mesh)
        if "handle" in state:
            state["handle"].visible = bool(box.value)

    box.on_update(toggle)
    return box


def run_mesh(folder: Path, kind: str) -> Optional[Path]:
    """The mesh a run exported, preferring the textured one: the stylized mesh of a stylization, the source
    mesh of a reconstruction."""
    mesh = Path(folder) / "mesh"
    stem = "stylized" if kind == "stylization" else "source"
    for pattern in (f"{stem}*_textured.glb", f"{stem}*.ply"):
        found = sorted(p for p in mesh.glob(pattern) if "displacement" not in p.name)
        if found:
            return found[0]
    return None


def add_facts(viewer: Any, lines: Sequence[str]) -> Any:
    """A markdown panel of the run's facts (prompt, steps, metrics, the judge's block)."""
    with viewer.server.gui.add_folder("Run"):
        return viewer.server.gui.add_markdown("\n\n".join(lines))


def run_facts(run: Any) -> list[str]:
    """What a user asks of a finished run first, as markdown lines."""
    m, lines = run.metrics, [f"**{run.kind}** `{Path(run.folder).name}`"]
    if m.get("prompt"):
        lines.append(f"prompt: *{m['prompt']}*")
    if m.get("steps") is not None:
        lines.append(f"steps: {m['steps']}")
    if m.get("psnr") is not None:
        lines.append(f"PSNR {m['psnr']:.2f} dB ({m.get('evaluated_on', 'held-out views')})")
    judge = (m.get("judge") or {}).get("stylized") or {}
    if judge:
        per_view = judge.get("per_view") or []
        hits = sum(1 for v in per_view if v.get("target_rank", 99) < 5)
        lines.append(f"judge: P(target) {(m['judge'].get('source') or {}).get('mean_target_prob', 0):.4f} → "
                     f"{judge.get('mean_target_prob', 0):.3f}; top-5 on {hits}/{len(per_view)} held-out views")
    if m.get("stamp"):
        lines.append(f"guide: {m['stamp'].strip('_')} (not CLIP)")
    return lines
