"""Before/after comparison of a stylized mesh against its source mesh.

Distances are Euclidean, in world units. Point-to-mesh distance is the exact
point-to-triangle distance, minimised over candidate triangles found with a
``scipy.spatial.cKDTree`` on dense area-uniform surface samples plus all face
centroids (k nearest candidates per query point), refined over the 1-ring of
the best candidate for points near the surface (see ``SurfaceDistance``).

Conventions (stated in every ``compare_meshes`` result under ``"convention"``):
- ``chamfer`` (L1 convention): ``0.5 * (mean_a d(a, B) + mean_b d(b, A))`` over
  ``n_samples`` area-uniform samples a on the stylized mesh and b on the source.
- ``chamfer_l2``: the same with squared distances.
- ``hausdorff``: ``max(max_a d(a, B), max_b d(b, A))`` over the same samples.
- ``vertex_*``: per-vertex distance from each stylized vertex to the source
  surface; signed (positive = outside the source) when ``source_sdf`` is given.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from nerfart_plugin.errors import ConfigError, DataError
from nerfart_plugin.export.mesh import field_device
from nerfart_plugin.fields.analytic import AnalyticSDF
from nerfart_plugin.fields.field import Field

log = logging.getLogger(__name__)

SdfLike = Callable[[torch.Tensor], torch.Tensor] | Any


def _check_mesh(mesh: trimesh.Trimesh, name: str) -> None:
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise DataError(f"{name} mesh is empty or not a triangle mesh; extract/load a non-empty mesh first.")


class SurfaceDistance:
    """Nearest-surface distance queries against one triangle mesh.

    Step 1: k nearest candidates (dense surface samples + face centroids) in a
    cKDTree give k candidate triangles; exact point-triangle distances are taken.
    Step 2 (refinement): for query points closer than ~2 sample spacings to the
    surface, where a missed triangle would matter most, the distances to all
    triangles sharing a vertex with the best candidate are also taken.
    """

    def __init__(self, mesh: trimesh.Trimesh, n_samples: int = 100_000, k: int = 8, seed: int = 0) -> None:
        _check_mesh(mesh, "Target")
        self.mesh, self.k = mesh, int(k)
        pts, fid = trimesh.sample.sample_surface(mesh, int(n_samples), seed=seed)
        cand = np.concatenate([pts, mesh.triangles_center])
        self.cand_face = np.concatenate([fid, np.arange(len(mesh.faces))])
        self.tree = cKDTree(cand)
        self.triangles = np.asarray(mesh.triangles)
        self.spacing = float(np.sqrt(mesh.area / len(cand)))
        self._ring: np.ndarray | None = None

    @property
    def face_ring(self) -> np.ndarray:
        """[F, M] faces sharing a vertex with each face (padded with the face itself)."""
        if self._ring is None:
            vf = np.asarray(self.mesh.vertex_faces)  # [V, maxdeg], -1 padded
            ring = vf[np.asarray(self.mesh.faces)].reshape(len(self.mesh.faces), -1)
            own = np.arange(len(ring))[:, None]
            self._ring = np.where(ring < 0, own, ring)
        return self._ring

    def _tri_closest(self, p: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances [B,m] and closest points [B,m,3] from points p [B,3] to triangles faces [B,m]."""
        m = faces.shape[1]
        pp = np.repeat(p, m, axis=0)
        cp = trimesh.triangles.closest_point(self.triangles[faces.ravel()], pp)
        return np.linalg.norm(cp - pp, axis=1).reshape(len(p), m), cp.reshape(len(p), m, 3)

    def query(self, points: np.ndarray, batch: int = 32_768, return_closest: bool = False):
        """Unsigned distance [P] from points [P,3] to the mesh surface (world units).

        With ``return_closest=True`` also returns the closest surface points [P,3]
        and the index [P] of the face they lie on.
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.empty(len(points))
        closest = np.empty((len(points), 3))
        face_id = np.empty(len(points), dtype=np.int64)
        k = min(self.k, len(self.cand_face))
        for s in range(0, len(points), batch):
            p = points[s : s + batch]
            _, idx = self.tree.query(p, k=k, workers=-1)
            faces = self.cand_face[idx.reshape(len(p), k)]  # [B,k]
            d, cp = self._tri_closest(p, faces)
            j = d.argmin(axis=1)
            rows = np.arange(len(p))
            best, best_cp, best_f = d[rows, j], cp[rows, j], faces[rows, j]
            near = np.flatnonzero(best < 2.0 * self.spacing)
            if len(near):
                ring = self.face_ring[best_f[near]]
                d2, cp2 = self._tri_closest(p[near], ring)
                j2 = d2.argmin(axis=1)
                r2 = np.arange(len(near))
                better = d2[r2, j2] < best[near]
                upd = near[better]
                best[upd] = d2[r2, j2][better]
                best_cp[upd] = cp2[r2, j2][better]
                best_f[upd] = ring[r2, j2][better]
            out[s : s + batch], closest[s : s + batch], face_id[s : s + batch] = best, best_cp, best_f
        return (out, closest, face_id) if return_closest else out


def evaluate_sdf(source_sdf: SdfLike, points: np.ndarray, chunk: int = 65_536) -> np.ndarray:
    """Evaluate an SDF on points [P,3] -> [P] (numpy float64).

    ``source_sdf`` is a Field (its ``signed_distance()``; it must have one: volsdf/neus), or any
    callable taking a float32 tensor [N,3] (or numpy array) and returning [N].
    """
    fn = source_sdf
    device = torch.device("cpu")
    if isinstance(source_sdf, Field):
        fn = source_sdf.signed_distance()
        if fn is None:
            raise ConfigError(
                "source_sdf is a density field; signed distances need an SDF field (volsdf/neus) or "
                "an SDF callable. Pass source_sdf=None for unsigned distances."
            )

        device = field_device(source_sdf)
    out = np.empty(len(points))
    with torch.no_grad():
        for s in range(0, len(points), chunk):
            x = torch.as_tensor(np.asarray(points[s : s + chunk]), dtype=torch.float32, device=device)
            val = fn(x)
            if isinstance(val, torch.Tensor):
                val = val.detach().float().cpu().numpy()
            out[s : s + chunk] = np.asarray(val, dtype=np.float64).reshape(-1)
    return out


def vertex_distances(
    stylized: trimesh.Trimesh,
    source: trimesh.Trimesh,
    source_sdf: SdfLike | None = None,
    n_samples: int = 100_000,
    seed: int = 0,
    sign_from_normals: bool = False,
) -> np.ndarray:
    """Distance [V] from each stylized vertex to the source surface (world units).

    Unsigned nearest-surface distance by default. Signed (positive = the vertex lies
    outside the source) when ``source_sdf`` is given (sign of the source SDF at the
    vertex), or when ``sign_from_normals=True`` (sign of (vertex - closest point) .
    normal of the closest source face; needs consistently outward source normals).
    """
    _check_mesh(stylized, "Stylized")
    verts = np.asarray(stylized.vertices)
    d, cp, fid = SurfaceDistance(source, n_samples=n_samples, seed=seed).query(verts, return_closest=True)
    if source_sdf is not None:
        d = np.where(evaluate_sdf(source_sdf, verts) < 0, -d, d)
    elif sign_from_normals:
        side = np.einsum("ij,ij->i", verts - cp, np.asarray(source.face_normals)[fid])
        d = np.where(side < 0, -d, d)
    return d


def compare_meshes(
    stylized: trimesh.Trimesh,
    source: trimesh.Trimesh,
    n_samples: int = 100_000,
    source_sdf: SdfLike | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """Metrics (JSON-ready floats/ints, world units) comparing ``stylized`` to ``source``.

    Keys: chamfer, chamfer_l2, hausdorff, mean_stylized_to_source,
    mean_source_to_stylized, vertex_mean_abs, vertex_max_abs, vertex_rms,
    (signed only) vertex_mean_signed, vertex_fraction_outward, plus mesh sizes,
    n_samples, signed and the convention string.
    """
    _check_mesh(stylized, "Stylized")
    _check_mesh(source, "Source")
    a, _ = trimesh.sample.sample_surface(stylized, n_samples, seed=seed)
    b, _ = trimesh.sample.sample_surface(source, n_samples, seed=seed + 1)
    to_source = SurfaceDistance(source, n_samples=n_samples, seed=seed + 2)
    to_stylized = SurfaceDistance(stylized, n_samples=n_samples, seed=seed + 3)
    d_ab, d_ba = to_source.query(a), to_stylized.query(b)
    v = to_source.query(stylized.vertices)
    metrics: dict[str, Any] = {
        "chamfer": float(0.5 * (d_ab.mean() + d_ba.mean())),
        "chamfer_l2": float(0.5 * ((d_ab**2).mean() + (d_ba**2).mean())),
        "hausdorff": float(max(d_ab.max(), d_ba.max())),
        "mean_stylized_to_source": float(d_ab.mean()),
        "mean_source_to_stylized": float(d_ba.mean()),
        "vertex_mean_abs": float(v.mean()),
        "vertex_max_abs": float(v.max()),
        "vertex_rms": float(np.sqrt((v**2).mean())),
        "stylized_vertices": len(stylized.vertices),
        "stylized_faces": len(stylized.faces),
        "source_vertices": len(source.vertices),
        "source_faces": len(source.faces),
        "n_samples": int(n_samples),
        "signed": source_sdf is not None,
        "convention": (
            "world units; chamfer = 0.5*(mean_a d(a,B) + mean_b d(b,A)) of Euclidean (L1-style) "
            "distances over n_samples area-uniform samples each; chamfer_l2 uses squared distances; "
            "hausdorff = max of both directed maxima over the same samples"
        ),
    }
    if source_sdf is not None:
        signed = np.where(evaluate_sdf(source_sdf, np.asarray(stylized.vertices)) < 0, -v, v)
        metrics["vertex_mean_signed"] = float(signed.mean())
        metrics["vertex_fraction_outward"] = float((signed > 0).mean())
    return metrics


def displacement_mesh(
    stylized: trimesh.Trimesh,
    distances: np.ndarray,
    cmap: str = "coolwarm",
    vmax: float | None = None,
) -> trimesh.Trimesh:
    """Copy of ``stylized`` coloured by per-vertex ``distances`` [V] with a diverging colormap.

    Colours map [-vmax, vmax] (default vmax = max |distance|) so 0 is the colormap's
    centre (white/grey for coolwarm), outward blue->red for positive. The raw values
    are kept in ``vertex_attributes["displacement"]`` (written to PLY as a vertex
    property). Save with ``export.mesh.export_mesh(mesh, "displacement.ply")``.
    """
    import matplotlib

    distances = np.asarray(distances, dtype=np.float64).reshape(-1)
    if len(distances) != len(stylized.vertices):
        raise DataError(
            f"displacement_mesh got {len(distances)} distances for a mesh with {len(stylized.vertices)} "
            "vertices; compute them with vertex_distances(stylized, source)."
        )
    vmax = float(np.abs(distances).max()) if vmax is None else float(vmax)
    vmax = vmax if vmax > 0 else 1.0
    rgba = matplotlib.colormaps[cmap]((distances / vmax + 1.0) / 2.0)
    out = trimesh.Trimesh(vertices=np.array(stylized.vertices), faces=np.array(stylized.faces), process=False)
    out.visual = trimesh.visual.ColorVisuals(out, vertex_colors=(rgba * 255).round().astype(np.uint8))
    out.vertex_attributes["displacement"] = distances.astype(np.float32)
    out.metadata["displacement_vmax"] = vmax
    return out


def chamfer_to_analytic(mesh, field: AnalyticSDF, n_samples: int = 100_000, seed: int = 0) -> dict[str, float]:
    """Accuracy of ``mesh`` against the TRUE zero level set of an exact analytic SDF.

    mesh -> surface: |sdf| at ``n_samples`` area-uniform samples on the mesh (exact,
    since the SDF is an exact distance). surface -> mesh: distance from
    ``n_samples`` samples of the analytic surface to the mesh
    (``compare.SurfaceDistance``). ``chamfer`` = mean of the two directed means
    (L1 convention, world units); ``hausdorff`` = max of the two directed maxima.
    """
    pts, _ = trimesh.sample.sample_surface(mesh, n_samples, seed=seed)
    with torch.no_grad():
        d_mesh = field.sdf(torch.as_tensor(pts, dtype=torch.float32)).abs().double().numpy()
    d_true = SurfaceDistance(mesh, n_samples=n_samples, seed=seed + 1).query(field.sample_surface(n_samples, seed + 2))
    return {
        "mesh_to_surface": float(d_mesh.mean()),
        "surface_to_mesh": float(d_true.mean()),
        "chamfer": float(0.5 * (d_mesh.mean() + d_true.mean())),
        "hausdorff": float(max(d_mesh.max(), d_true.max())),
    }
