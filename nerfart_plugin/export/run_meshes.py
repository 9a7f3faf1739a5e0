"""The meshes a run folder holds: a field's mesh written in ``export.frame`` (plus its textured copy), and
the source mesh that a stylization shares with its reconstruction instead of extracting it again.

A field's mesh depends only on the field's tensors, the scene (for the output frame) and the
``export`` settings, so :func:`export_source_mesh` keys it by exactly those: the reconstruction
writes ``mesh/source.*`` with the key beside it, and a stylization of that field copies the files
(and reads the field-frame mesh back) when the key matches, else extracts and bakes as usual.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch
import trimesh

from nerfart_plugin.config.validate import result_settings
from nerfart_plugin.errors import NerfArtError
from nerfart_plugin.export import MeshExtractor
from nerfart_plugin.export.texture import bake_texture, export_textured
from nerfart_plugin.export.world_frame import mesh_in_frame, write_mesh_in_frame
from nerfart_plugin.utils.io import atomic_path, atomic_write_json, config_hash

log = logging.getLogger("nerfart_plugin")

#: the hidden cache beside a run's meshes: ``<stem>.npz`` (the field-frame mesh) and ``<stem>.json`` (its key)
CACHE_DIR = ".cache"


def export_mesh(scene: Any, field: Any, stem: Path, texture: bool = True):
    """The mesh of ``field`` (marching cubes, ``export.*``) written as ``stem.<fmt>`` for each format in
    ``export.frame`` (the file says which), plus ``stem_textured.obj/.mtl/.png/.glb`` when ``export.texture``;
    returns the mesh in the field's frame (for comparisons), None (with a warning) when the field has no
    surface at the level."""

    ec = scene.cfg.export
    ex = MeshExtractor(resolution=ec.resolution, bound=float(field.bound), chunk=ec.chunk, level=ec.level,
                       remove_floaters=ec.remove_floaters)
    try:
        mesh = ex.extract(field)
    except NerfArtError as exc:
        log.warning("no mesh for %s: %s", stem, exc)
        return None
    for fmt in ec.formats:
        write_in_frame(scene, mesh, stem.with_name(f"{stem.name}.{fmt}"))
    if texture and ec.texture:

        try:
            textured = bake_texture(mesh, field, size=ec.texture_size, chunk=ec.chunk, faces=ec.texture_faces)
        except NerfArtError as exc:
            log.warning("no textured mesh for %s: %s", stem, exc)
        else:
            export_textured(in_frame(scene, textured), stem.with_name(f"{stem.name}_textured"))
    return mesh


def in_frame(scene: Any, mesh: Any) -> Any:
    """``mesh`` (field frame: normalized, or NDC for forward-facing captures) in ``export.frame``."""

    return mesh_in_frame(mesh, scene.cfg.export.frame, scene.cameras)


def write_in_frame(scene: Any, mesh: Any, path: Path) -> Path:
    """Write a field-frame mesh in ``export.frame``, saying so in the file (see :mod:`export.frames`)."""

    return write_mesh_in_frame(mesh, path, scene.cfg.export.frame, scene.cameras)


# ---------------------------------------------------------------------- the shared source mesh
def tensors_hash(module: torch.nn.Module) -> str:
    """SHA-256 of a module's parameters and buffers (names, dtypes, shapes and bytes, in name order)."""
    h = hashlib.sha256()
    for name, t in sorted(module.state_dict().items()):
        h.update(f"{name}:{t.dtype}:{tuple(t.shape)}".encode())
        h.update(t.detach().to("cpu").contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def mesh_key(scene: Any, field: Any) -> str:
    """What a field's exported mesh files depend on: the field's tensors, the scene (its cameras place the
    output frame) and the export settings that change results."""
    return config_hash({"field": tensors_hash(field), "scene": scene.scene.content_hash,
                        "export": result_settings(scene.cfg.export)}, n=64)


def _outputs(stem: Path, formats: list[str]) -> list[Path]:
    """The files :func:`export_mesh` may write for ``stem`` (those that exist)."""
    names = [stem.with_name(f"{stem.name}.{f}") for f in formats]
    names += [stem.with_name(f"{stem.name}_textured{s}") for s in (".obj", ".mtl", ".png", ".glb")]
    return [p for p in names if p.is_file()]


def _cache(stem: Path) -> tuple[Path, Path]:
    return stem.parent / CACHE_DIR / f"{stem.name}.npz", stem.parent / CACHE_DIR / f"{stem.name}.json"


def remember_mesh(stem: Path, mesh: Any, key: str, formats: list[str]) -> None:
    """Store the field-frame ``mesh`` and its ``key`` beside the files written for ``stem`` (``formats``)."""
    npz, meta = _cache(stem)
    npz.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"vertices": np.asarray(mesh.vertices), "faces": np.asarray(mesh.faces)}
    colors = getattr(mesh.visual, "vertex_colors", None)
    if colors is not None and len(colors) == len(mesh.vertices):
        arrays["vertex_colors"] = np.asarray(colors)
    with atomic_path(npz) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    atomic_write_json(meta, {"key": key, "files": [p.name for p in _outputs(stem, formats)]})


def recall_mesh(stem: Path, key: str) -> Optional[tuple[Any, list[str]]]:
    """The field-frame mesh stored for ``stem`` under ``key`` and the names of its files, when every one of
    them is still there; else None."""

    npz, meta = _cache(stem)
    try:
        stored = json.loads(meta.read_text())
        files = list(stored["files"])
        if stored.get("key") != key or not all((stem.parent / n).is_file() for n in files):
            return None
        with np.load(npz) as data:
            mesh = trimesh.Trimesh(vertices=data["vertices"], faces=data["faces"], process=False,
                                   vertex_colors=data["vertex_colors"] if "vertex_colors" in data else None)
        return mesh, files
    except (OSError, ValueError, KeyError, TypeError):
        return None


def export_source_mesh(scene: Any, field: Any, stem: Path, shared: Optional[Path] = None):
    """:func:`export_mesh` of a source field into ``stem``, remembered under its :func:`mesh_key`. When
    ``shared`` (the same stem in the source run's folder) holds the mesh of this very key, its files are
    copied instead of extracting and baking again. Returns the field-frame mesh (None: no surface)."""
    key = mesh_key(scene, field)
    if shared is not None and shared != stem:
        recalled = recall_mesh(shared, key)
        if recalled is not None:
            mesh, files = recalled
            stem.parent.mkdir(parents=True, exist_ok=True)
            for name in files:
                shutil.copy2(shared.parent / name, stem.parent / name)
            remember_mesh(stem, mesh, key, scene.cfg.export.formats)
            log.info("source mesh: copied from %s (the same field and export settings)", shared.parent)
            return mesh
    mesh = export_mesh(scene, field, stem)
    if mesh is not None:
        remember_mesh(stem, mesh, key, scene.cfg.export.formats)
    return mesh
