"""Which frame an exported mesh is in: the capture's world frame (default) or the normalized one.

Fields are trained in a normalized frame (``Scene.normalization`` T maps the
capture's world coordinates into it: ``x_norm = T @ x_world``, a similarity
that fits the scene into the unit sphere), and forward-facing (LLFF) scenes
in NDC on top of it. A mesh opened next to the photos' COLMAP model, the
capture's point cloud or other tools' reconstructions must be in the
capture's own frame: :func:`to_frame` maps the marching-cubes vertices back
(NDC -> normalized -> world), and :func:`frame_metadata` says which frame a
file is in (written into the file by :func:`nerfart_plugin.export.mesh.export_mesh`:
PLY/OBJ comments, glTF ``extras``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import numpy as np
import trimesh

from nerfart_plugin.cameras.capture import ndc_to_normalized
from nerfart_plugin.errors import ConfigError
from nerfart_plugin.export.mesh import export_mesh

FRAMES = ("world", "normalized")


def to_frame(mesh: trimesh.Trimesh, frame: str, normalization: np.ndarray,
             ndc: Optional[dict[str, float]] = None) -> trimesh.Trimesh:
    """A copy of ``mesh`` (vertices in the field's frame) in ``frame``.

    Args:
        mesh: marching-cubes mesh of a field.
        frame: "world" (the capture's frame, T^-1 applied) or "normalized" (as trained).
        normalization: T [4,4], ``x_norm = T @ x_world``.
        ndc: for NDC fields, ``{"fx", "fy", "W", "H", "near_plane"}`` of the NDC warp; faces with a
            vertex at infinity (the far plane) are dropped.
    """
    if frame not in FRAMES:
        raise ConfigError(f"export.frame={frame!r}: use world (the capture's frame) or normalized (as trained).")
    out = mesh.copy()
    verts = np.asarray(out.vertices, dtype=np.float64)
    if ndc is not None:
        verts, finite = ndc_to_normalized(verts, ndc["fx"], ndc["fy"], ndc["W"], ndc["H"], ndc.get("near_plane", 1.0))
        out.vertices = verts
        keep = finite[out.faces].all(1)
        if not keep.all():
            out.update_faces(keep)
            out.remove_unreferenced_vertices()
        verts = np.asarray(out.vertices, dtype=np.float64)
    if frame == "world":
        T_inv = np.linalg.inv(np.asarray(normalization, dtype=np.float64))
        out.vertices = verts @ T_inv[:3, :3].T + T_inv[:3, 3]
    return out


def frame_metadata(frame: str, normalization: np.ndarray, ndc: bool = False) -> dict[str, Any]:
    """What a mesh file says about its coordinates (JSON-ready)."""
    T = np.asarray(normalization, dtype=np.float64)
    scale = float(np.cbrt(abs(np.linalg.det(T[:3, :3]))))
    text = ("the capture's world frame (the cameras' frame of the input poses)" if frame == "world" else
            "the normalized training frame (x_norm = T @ x_world; the scene fits the unit sphere)")
    if ndc and frame == "normalized":
        text += ", converted from NDC"
    return {"generator": "nerfart_plugin", "frame": frame, "description": text,
            "normalization_T": T.round(10).tolist(), "world_units_per_normalized_unit": 1.0 / scale}


def mesh_in_frame(mesh: trimesh.Trimesh, frame: str, cams: Any) -> trimesh.Trimesh:
    """A field-frame ``mesh`` (normalized, or NDC for forward-facing captures) in ``frame``, for the capture
    of ``cams`` (:class:`~nerfart_plugin.cameras.capture.CaptureCameras`)."""
    ndc = None
    if cams.ndc:
        K = np.asarray(cams.K[0], dtype=np.float64)
        ndc = {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "W": float(cams.width), "H": float(cams.height),
               "near_plane": 1.0}
    return to_frame(mesh, frame, cams.normalization, ndc)


def write_mesh_in_frame(mesh: trimesh.Trimesh, path: Path, frame: str, cams: Any) -> Path:
    """Write a field-frame ``mesh`` in ``frame``, saying so in the file (:func:`frame_metadata`)."""

    return export_mesh(mesh_in_frame(mesh, frame, cams), path, meta=frame_metadata(frame, cams.normalization, cams.ndc))
