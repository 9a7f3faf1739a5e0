"""PyVista mesh viewer: one mesh, or source vs stylized side by side.

    python -m nerfart_plugin.viewer.mesh MESH [MESH2] [--screenshot out.png]
                                  [--scalars {auto,rgb,displacement,none}]
                                  [--window-size W H]

- one mesh: shown with its vertex colours (grey if it has none);
- two meshes: side by side (``pv.Plotter(shape=(1, 2))``) with linked cameras;
  the second is coloured by its signed displacement to the first (sign from the
  source's face normals, + = outward; ``export.compare.vertex_distances``,
  diverging colormap) unless ``--scalars rgb``.
- ``--screenshot`` renders off-screen and writes a PNG.

Off-screen rendering without a display: the VTK >= 9.4 PyPI wheels ship an EGL
render window that draws with Mesa's llvmpipe software rasteriser. It needs the
Debian packages ``libegl1 libegl-mesa0 libgl1-mesa-dri`` (plus ``libgl1``, ``libglx-mesa0``).
When no ``DISPLAY`` is set, this module selects that window up front
(``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow``) so VTK does not first try, and
warn about, an X server. No Xvfb is needed.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from nerfart_plugin.errors import ConfigError, DataError, NerfArtError
from nerfart_plugin.export.compare import vertex_distances
from nerfart_plugin.utils.images import save_image

log = logging.getLogger(__name__)

SCALAR_MODES = ("auto", "rgb", "displacement", "none")


def _has_display() -> bool:
    return sys.platform in ("win32", "darwin") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _prepare_offscreen() -> None:
    """Pick VTK's EGL (headless) render window when there is no display."""
    if not _has_display():
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def load_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """Read a mesh file (.ply/.obj/.glb/...) as one ``trimesh.Trimesh``; DataError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"Mesh file not found: {path}. Check the path (export writes e.g. <run>/mesh.ply).")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise DataError(f"Could not read mesh file {path}: {exc}. Is it a valid PLY/OBJ/GLB mesh?") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise DataError(f"Mesh file {path} contains no triangles; re-export it (nerfart_plugin.export).")
    return mesh


def _vertex_rgb(mesh: trimesh.Trimesh) -> np.ndarray | None:
    """[V,3] uint8 vertex colours, or None if the mesh has none."""
    vis = mesh.visual
    if getattr(vis, "kind", None) == "texture":
        try:
            vis = vis.to_color()
        except Exception:  # noqa: BLE001  # pragma: no cover - odd textures
            return None
    if getattr(vis, "kind", None) != "vertex":
        return None
    return np.asarray(vis.vertex_colors)[:, :3].astype(np.uint8)


def to_pyvista(mesh: trimesh.Trimesh):
    """trimesh -> pyvista.PolyData with point array "RGB" (uint8) when coloured."""
    import pyvista as pv

    faces = np.hstack([np.full((len(mesh.faces), 1), 3), np.asarray(mesh.faces)]).astype(np.int64).ravel()
    poly = pv.PolyData(np.asarray(mesh.vertices, dtype=np.float64), faces)
    rgb = _vertex_rgb(mesh)
    if rgb is not None:
        poly.point_data["RGB"] = rgb
    return poly


def render_meshes(
    meshes: Sequence[str | os.PathLike | trimesh.Trimesh],
    screenshot: str | os.PathLike | None = None,
    scalars: str = "auto",
    window_size: tuple[int, int] | None = None,
    labels: Sequence[str] | None = None,
    off_screen: bool | None = None,
    n_samples: int = 50_000,
    cameras: str | os.PathLike | dict | None = "auto",
) -> np.ndarray | None:
    """Show (or screenshot) one mesh, or two side by side with linked cameras.

    Args:
        meshes: 1 or 2 paths or trimesh meshes (the second = stylized).
        screenshot: PNG path; renders off-screen and writes the image atomically.
        scalars: "auto" (vertex colours; with two meshes the second shows its
            displacement to the first), "rgb", "displacement" (two meshes only), "none".
        window_size: (W, H) pixels; default (800, 800) per mesh.
        labels: subplot titles; default file names / ("source", "stylized").
        off_screen: force off-screen; default = True when screenshotting.
        n_samples: surface samples for the displacement distance.
        cameras: the run's ``cameras.json`` (or its dict, see
            :func:`nerfart_plugin.cameras.capture.viewer_cameras`): the view opens at the
            capture's front camera with its up vector; "auto" looks for ``cameras.json`` in the
            mesh's run folder (``<run>/mesh/x.ply`` -> ``<run>/cameras.json``); None: an
            isometric view.
    Returns:
        The rendered image [H,W,3] uint8 when ``screenshot`` is given, else None.
    """
    if scalars not in SCALAR_MODES:
        raise ConfigError(f"--scalars {scalars!r} is not one of {', '.join(SCALAR_MODES)}.")
    if not 1 <= len(meshes) <= 2:
        raise ConfigError(f"render_meshes takes 1 or 2 meshes, got {len(meshes)}.")
    if scalars == "displacement" and len(meshes) != 2:
        raise ConfigError("--scalars displacement needs two meshes: SOURCE STYLIZED.")
    window_size = checked_window_size(window_size) if window_size else (800 * len(meshes), 800)
    if n_samples < 1:
        raise ConfigError(f"--samples {n_samples}: give a positive number of surface samples (default 50000).")
    tms = [m if isinstance(m, trimesh.Trimesh) else load_mesh(m) for m in meshes]
    view = capture_view(cameras, meshes)
    if labels is None:
        labels = [
            Path(m).name if not isinstance(m, trimesh.Trimesh) else n for m, n in zip(meshes, ("source", "stylized"))
        ]
    off_screen = screenshot is not None if off_screen is None else off_screen
    if not off_screen and not _has_display():
        raise NerfArtError(
            "No display found for the interactive viewer; pass --screenshot out.png to render off-screen."
        )
    if off_screen:
        _prepare_offscreen()
    import pyvista as pv

    n = len(tms)
    pl = pv.Plotter(shape=(1, n), off_screen=off_screen, window_size=list(window_size), border=False)
    pl.set_background("white")
    for i, tm in enumerate(tms):
        pl.subplot(0, i)
        poly = to_pyvista(tm)
        show_disp = i == 1 and (scalars == "displacement" or (scalars == "auto"))
        if show_disp:

            d = vertex_distances(tm, tms[0], n_samples=n_samples, sign_from_normals=True)
            poly.point_data["displacement"] = d
            vmax = float(np.abs(d).max()) or 1.0
            pl.add_mesh(
                poly,
                scalars="displacement",
                cmap="coolwarm",
                clim=(-vmax, vmax),
                smooth_shading=True,
                scalar_bar_args={
                    "title": "displacement (+ outward)",
                    "color": "black",
                    "vertical": False,
                    "position_x": 0.2,
                    "position_y": 0.03,
                    "width": 0.6,
                    "height": 0.08,
                    "title_font_size": 12,
                    "label_font_size": 10,
                    "n_labels": 3,
                    "fmt": "%.3g",
                },
            )
        elif scalars != "none" and "RGB" in poly.point_data:
            pl.add_mesh(poly, scalars="RGB", rgb=True, smooth_shading=True)
        else:
            pl.add_mesh(poly, color="lightgrey", smooth_shading=True)
        pl.add_text(str(labels[i]), font_size=10, color="black")
        if view is None:
            pl.camera_position = "iso"
        else:
            pl.camera_position = view
        pl.reset_camera()
    if n == 2:
        pl.link_views()
    try:
        if screenshot is None:
            pl.show()
            return None
        img = pl.screenshot(None, return_img=True)
    finally:
        if screenshot is not None:
            pl.close()

    save_image(img, screenshot)
    log.info("Wrote screenshot %s", screenshot)
    return np.asarray(img)[..., :3]


def find_cameras(meshes: Sequence[str | os.PathLike | trimesh.Trimesh]) -> Path | None:
    """The ``cameras.json`` of the run a mesh file belongs to (its folder or the folder above), if any."""
    for m in meshes:
        if isinstance(m, trimesh.Trimesh):
            continue
        for folder in (Path(m).resolve().parent, Path(m).resolve().parent.parent):
            if (folder / "cameras.json").is_file():
                return folder / "cameras.json"
    return None


def capture_view(cameras: str | os.PathLike | dict | None,
                 meshes: Sequence[str | os.PathLike | trimesh.Trimesh] = ()) -> list | None:
    """PyVista ``camera_position`` ``[eye, focal point, view up]`` at the capture's front camera, looking at
    the cameras' look-at centre with the capture's up vector; None without cameras (isometric view)."""

    if cameras == "auto":
        cameras = find_cameras(meshes)
        if cameras is None:
            log.info("no cameras.json beside the meshes: opening on an isometric view")
            return None
    if cameras is None:
        return None
    if not isinstance(cameras, dict):
        path = Path(cameras)
        try:
            cameras = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise NerfArtError(f"Cannot read cameras {path}: {exc}. Pass the run's cameras.json (or --no-cameras).") from exc
    try:
        c2w = np.asarray(cameras["c2w"], dtype=np.float64)
        eye = c2w[int(cameras["front"]), :3, 3]
        return [tuple(eye), tuple(np.asarray(cameras["centre"], dtype=np.float64)),
                tuple(np.asarray(cameras["up"], dtype=np.float64))]
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise NerfArtError(f"cameras file is malformed ({exc}): it needs c2w, front, centre and up, as the "
                           "pipeline writes them (cameras.json in the run folder).") from exc


#: the window / screenshot sides the viewer accepts (pixels)
WINDOW_SIDES = (16, 16384)


def checked_window_size(size: Sequence[int]) -> tuple[int, int]:
    """``(W, H)`` when both sides are whole pixels in :data:`WINDOW_SIDES`, else a ConfigError."""
    lo, hi = WINDOW_SIDES
    if len(size) != 2 or not all(isinstance(v, int) and lo <= v <= hi for v in size):
        raise ConfigError(f"--window-size {' '.join(map(str, size))}: give the width and height in pixels, "
                          f"each from {lo} to {hi} (e.g. --window-size 1600 800).")
    return int(size[0]), int(size[1])


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m nerfart_plugin.viewer.mesh",
        description="View a mesh, or a source and a stylized mesh side by side (linked cameras, "
        "displacement colormap on the second).",
    )
    parser.add_argument(
        "meshes", nargs="+", metavar="MESH", help="1 or 2 mesh files (.ply/.obj/.glb): SOURCE [STYLIZED]"
    )
    parser.add_argument(
        "--screenshot", metavar="PNG", help="render off-screen and save a PNG instead of opening a window"
    )
    parser.add_argument("--scalars", default="auto", choices=SCALAR_MODES, help="colouring (default: auto)")
    parser.add_argument("--window-size", nargs=2, type=int, metavar=("W", "H"), help="window/screenshot size in pixels")
    parser.add_argument("--samples", type=int, default=50_000, help="surface samples for displacement distances")
    parser.add_argument("--cameras", metavar="JSON", default="auto",
                        help="the run's cameras.json (default: found beside the meshes): open on the capture's front view")
    parser.add_argument("--no-cameras", action="store_true", help="ignore the capture's cameras (isometric view)")
    args = parser.parse_args(argv)
    if len(args.meshes) > 2:
        parser.error(f"at most 2 meshes, got {len(args.meshes)}")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        render_meshes(
            args.meshes,
            screenshot=args.screenshot,
            scalars=args.scalars,
            window_size=tuple(args.window_size) if args.window_size else None,
            n_samples=args.samples,
            cameras=None if args.no_cameras else args.cameras,
        )
    except NerfArtError as exc:
        parser.exit(2, f"error: {exc}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
