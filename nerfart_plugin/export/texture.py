"""Textured meshes: a UV atlas (xatlas) and a texture baked from the field's colour.

Vertex colours (``export/mesh.py``) carry one colour per vertex; Blender and
most viewers show them only with extra setup, and a 128^3 marching-cubes mesh
has too few vertices for the stylized detail. :func:`bake_texture` instead

1. decimates the mesh to ``faces`` triangles (VTK's quadric decimation through
   pyvista: a marching-cubes mesh has far more triangles than its shape needs,
   and the UV unwrap's time grows faster than linearly with them; the texture
   carries the colour detail) and unwraps it with xatlas (``xatlas.parametrize``:
   charts packed into one atlas; vertices on chart seams are duplicated);
2. rasterizes every atlas triangle into a ``size`` x ``size`` texture (OpenCV
   ``fillConvexPoly`` of the triangle's index), so each texel knows its
   triangle and, from barycentric coordinates, its 3D point and normal;
3. queries the field's colour there, seen head-on (``views`` directions
   looking at the surface averaged, as :meth:`MeshExtractor.colorize` does
   for vertices; one by default);
4. grows the charts by ``padding`` texels (OpenCV inpainting) so that
   bilinear filtering and mip-mapping do not bleed the background into seams.

:func:`export_textured` writes OBJ + MTL + PNG and a GLB with the texture
embedded (trimesh), atomically.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch
import trimesh
from PIL import Image

from nerfart_plugin.errors import ConfigError, NerfArtError
from nerfart_plugin.export.mesh import field_device, view_directions
from nerfart_plugin.utils.io import atomic_path

log = logging.getLogger(__name__)


def decimate(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    """``mesh`` reduced to about ``faces`` triangles (quadric decimation, pyvista/VTK); unchanged when it has
    no more than that, or ``faces`` is 0."""
    import pyvista as pv

    n = len(mesh.faces)
    if faces <= 0 or n <= faces:
        return mesh
    cells = np.hstack([np.full((n, 1), 3, dtype=np.int64), np.asarray(mesh.faces, dtype=np.int64)]).ravel()
    reduced = pv.PolyData(np.asarray(mesh.vertices, dtype=np.float64), cells).decimate(1.0 - faces / n)
    out = trimesh.Trimesh(np.asarray(reduced.points, dtype=np.float64), reduced.faces.reshape(-1, 4)[:, 1:],
                          process=False)
    log.info("Decimated the mesh from %d to %d triangles for its UV atlas (export.texture_faces=%d)", n,
             len(out.faces), faces)
    return out


def unwrap(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """xatlas UV atlas: ``(vmapping [V'] into mesh.vertices, faces [F,3] into V', uv [V',2] in [0,1])``."""
    import xatlas

    vmapping, faces, uv = xatlas.parametrize(np.asarray(mesh.vertices, dtype=np.float32),
                                             np.asarray(mesh.faces, dtype=np.uint32))
    return vmapping.astype(np.int64), faces.astype(np.int64), uv.astype(np.float64)


def rasterize_atlas(faces: np.ndarray, uv: np.ndarray, size: int) -> np.ndarray:
    """Triangle index of every texel ([size,size] int64, -1 where no triangle); row 0 is v = 1
    (image convention: OBJ/GLB texture coordinates have v up)."""
    import cv2

    ids = np.zeros((size, size, 3), dtype=np.uint8)  # triangle index + 1 in 24 bits
    pix = np.stack([uv[:, 0] * size - 0.5, (1.0 - uv[:, 1]) * size - 0.5], -1)
    shift = 4  # sub-pixel precision of cv2's rasterizer (1/16 px)
    tri_px = np.round(pix[faces] * (1 << shift)).astype(np.int32)
    for f, tri in enumerate(tri_px):
        code = f + 1
        cv2.fillConvexPoly(ids, tri, (code & 255, (code >> 8) & 255, (code >> 16) & 255), lineType=cv2.LINE_8,
                           shift=shift)
    index = ids[..., 0].astype(np.int64) | (ids[..., 1].astype(np.int64) << 8) | (ids[..., 2].astype(np.int64) << 16)
    return index - 1


def texel_points(vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray, uv: np.ndarray,
                 index: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the covered texels: their (row, col) [T,2], 3D points [T,3] and unit normals [T,3], from the
    barycentric coordinates of the texel centre in its triangle's UV triangle (clamped to the triangle)."""
    size = index.shape[0]
    rows, cols = np.nonzero(index >= 0)
    tri = index[rows, cols]
    p = np.stack([(cols + 0.5) / size, 1.0 - (rows + 0.5) / size], -1)
    a, b, c = (uv[faces[tri, k]] for k in range(3))
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) < 1e-20, 1e-20, den)
    w1 = (d11 * d20 - d01 * d21) / den
    w2 = (d00 * d21 - d01 * d20) / den
    bary = np.clip(np.stack([1.0 - w1 - w2, w1, w2], -1), 0.0, None)
    bary /= np.maximum(bary.sum(1, keepdims=True), 1e-12)
    corners = faces[tri]
    pts = (bary[..., None] * vertices[corners]).sum(1)
    nrm = (bary[..., None] * normals[corners]).sum(1)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return np.stack([rows, cols], -1), pts, nrm


@torch.no_grad()
def field_colors(field: Any, points: np.ndarray, normals: np.ndarray, views: int = 3, chunk: int = 65536) -> np.ndarray:
    """The field's colour [T,3] in [0,1] at surface ``points`` [T,3], averaged over ``views`` directions
    looking at the surface along ``-normals`` (as the vertex colours)."""
    device = field_device(field)
    x = torch.as_tensor(points, dtype=torch.float32, device=device)
    dirs = view_directions(-torch.as_tensor(normals, dtype=torch.float32, device=device), views)
    k = dirs.shape[1]
    rgb = torch.zeros(len(x), 3, device=device)
    step = max(1, chunk // k)
    for s in range(0, len(x), step):
        e = min(s + step, len(x))
        xs = x[s:e, None].expand(-1, k, -1).reshape(-1, 3)
        rgb[s:e] = field.forward(xs, dirs[s:e].reshape(-1, 3))["rgb"].float().reshape(e - s, k, 3).mean(1)
    return rgb.clamp(0, 1).cpu().numpy()


def bake_texture(mesh: trimesh.Trimesh, field: Any, size: int = 1024, views: int = 1, padding: int = 4,
                 chunk: int = 65536, faces: int = 0) -> trimesh.Trimesh:
    """A copy of ``mesh`` (decimated to ``faces`` triangles) with a UV atlas and a ``size`` x ``size`` texture
    of the field's colour.

    Args:
        mesh: world-space mesh of ``field`` (e.g. from :class:`MeshExtractor`).
        field: anything with ``forward(x [N,3], d [N,3]) -> {"rgb": [N,3]}``.
        size: texture side (pixels), 64..8192.
        faces: triangles of the textured copy (:func:`decimate`); 0: as many as ``mesh``.
        views: view directions averaged per texel (1: the colour seen head-on, along the inward normal;
            a texture has ~20x more points than the mesh has vertices, so each direction costs).
        padding: texels by which charts are grown into the empty atlas.
    Returns: a ``trimesh.Trimesh`` with ``TextureVisuals`` (uv, PIL image).
    """

    if not 64 <= int(size) <= 8192:
        raise ConfigError(f"export.texture_size={size}: use 64..8192 pixels.")
    if len(mesh.faces) == 0:
        raise NerfArtError("Cannot texture an empty mesh: the field has no surface at the extraction level.")
    mesh = decimate(mesh, int(faces))
    vmap, faces, uv = unwrap(mesh)
    vertices = np.asarray(mesh.vertices)[vmap]
    normals = np.asarray(mesh.vertex_normals)[vmap]
    index = rasterize_atlas(faces, uv, int(size))
    texels, pts, nrm = texel_points(vertices, normals, faces, uv, index)
    image = np.zeros((size, size, 3), dtype=np.uint8)
    image[texels[:, 0], texels[:, 1]] = np.round(field_colors(field, pts, nrm, views, chunk) * 255).astype(np.uint8)
    image = pad_charts(image, index < 0, padding)
    log.info("Baked a %dx%d texture: %d of the atlas's %d triangles cover %.0f%% of its texels", size, size,
             len(np.unique(index[index >= 0])), len(faces), 100.0 * float((index >= 0).mean()))
    visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(image))
    return trimesh.Trimesh(vertices=vertices, faces=faces, visual=visual, process=False)


def pad_charts(image: np.ndarray, empty: np.ndarray, padding: int) -> np.ndarray:
    """Fill the ``empty`` [H,W] texels within ``padding`` px of a chart from the chart (OpenCV Telea
    inpainting), so seams do not sample the black background; farther texels stay black."""
    import cv2

    if padding <= 0 or not empty.any():
        return image
    mask = empty.astype(np.uint8)
    filled = cv2.inpaint(image, mask, padding, cv2.INPAINT_TELEA)
    near = cv2.dilate((~empty).astype(np.uint8), np.ones((2 * padding + 1,) * 2, np.uint8)) > 0
    out = image.copy()
    out[empty & near] = filled[empty & near]
    return out


def export_textured(mesh: trimesh.Trimesh, stem: Path, formats: tuple[str, ...] = ("obj", "glb")) -> list[Path]:
    """Write a textured mesh as ``<stem>.obj`` (+ ``<stem>.mtl``, ``<stem>.png``) and/or ``<stem>.glb``
    (texture embedded), atomically. Returns the written paths."""
    stem = Path(stem)
    written: list[Path] = []
    if "obj" in formats:
        files = trimesh.exchange.obj.export_obj(mesh, include_texture=True, mtl_name=f"{stem.name}.mtl",
                                                return_texture=True)
        obj_text, textures = files
        for name, data in textures.items():  # the .mtl and the texture image it names
            target = stem.parent / (f"{stem.name}.mtl" if name.endswith(".mtl") else f"{stem.name}{Path(name).suffix}")
            if name.endswith(".mtl"):
                data = data.replace(Path(_image_name(textures)).name.encode(),
                                    f"{stem.name}{Path(_image_name(textures)).suffix}".encode())
            with atomic_path(target) as tmp:
                Path(tmp).write_bytes(data)
            written.append(target)
        with atomic_path(stem.with_name(f"{stem.name}.obj")) as tmp:
            Path(tmp).write_text(obj_text)
        written.append(stem.with_name(f"{stem.name}.obj"))
    if "glb" in formats:
        with atomic_path(stem.with_name(f"{stem.name}.glb")) as tmp:
            mesh.export(tmp, file_type="glb")
        written.append(stem.with_name(f"{stem.name}.glb"))
    log.info("Wrote textured mesh %s (%s)", stem, ", ".join(p.name for p in written))
    return written


def _image_name(textures: dict[str, bytes]) -> str:
    names = [n for n in textures if not n.endswith(".mtl")]
    if not names:
        raise NerfArtError("trimesh wrote no texture image for the OBJ export; the mesh has no texture.")
    return names[0]
