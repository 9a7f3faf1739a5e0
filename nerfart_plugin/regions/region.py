"""A region of a scene: a soft mask m(x) in [0, 1] in the capture's world frame, made of boxes, ellipsoids and
grids (lifted from 2D masks), combined by union, subtraction, intersection and inversion.

A region is resolution-free until it is bound to a run: :meth:`Region.bind` samples it on a small grid over the
run's field box (``resolution`` cells a side, read trilinearly) together with its geometry mask, the colour mask
dilated by ``margin`` (world units) so that a stylized shape may grow a little past the region. A shape's edge is
feathered outward over ``feather`` world units (``None``: two cells of the grid it is bound to). A shape may
reach past the scene's box: it is clipped there.

``save(path)`` writes one ``.npz`` (the shapes as JSON, grids as arrays); ``Region.load`` reads it back, checked
(a bad value names the file and the field). Its :attr:`content_hash` names it in a run's cache key.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import numpy as np
import torch
import torch.nn.functional as F

from nerfart_plugin.errors import ConfigError, DataError
from nerfart_plugin.fields.composite import RegionMask
from nerfart_plugin.regions.lift import lift_masks
from nerfart_plugin.utils.io import atomic_path

#: the layout of a region file
REGION_FORMAT = 1
#: cells a side of the grid a region is bound to
DEFAULT_RESOLUTION = 96
#: feather = this many cells of that grid when a shape gives none
AUTO_FEATHER_CELLS = 2.0
ArrayLike = Union[Sequence[float], np.ndarray, torch.Tensor]


def rotation_matrix(rotation: Optional[ArrayLike]) -> np.ndarray:
    """A rotation [3,3]: None (identity), XYZ Euler angles in degrees [3] (applied x, then y, then z), or a
    rotation matrix [3,3]."""
    if rotation is None:
        return np.eye(3)
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape == (3, 3):
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-4) or np.linalg.det(r) <= 0:
            raise ConfigError(f"region rotation: {r.tolist()} is not a rotation matrix (orthonormal, det +1).")
        return r
    if r.shape != (3,) or not np.isfinite(r).all():
        raise ConfigError(f"region rotation: {r.tolist()}: give 3 Euler angles in degrees (x, y, z) or a 3x3 matrix.")
    ax, ay, az = np.radians(r)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _vector(value: ArrayLike, name: str, positive: bool = False) -> np.ndarray:
    v = np.asarray(value.detach().cpu() if torch.is_tensor(value) else value, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ConfigError(f"region {name}: {np.asarray(value).tolist()}: give 3 finite numbers (x, y, z, world units).")
    if positive and (v <= 0).any():
        raise ConfigError(f"region {name}: {v.tolist()}: each half-size or radius must be > 0.")
    return v


def _feather(value: Optional[float]) -> Optional[float]:
    if value is None:
        return None
    f = float(value)
    if not math.isfinite(f) or f < 0:
        raise ConfigError(f"region feather={value!r}: a width in world units >= 0 (null: two cells of the grid).")
    return f


@dataclass(frozen=True)
class Region:
    """A soft mask over the world frame: a tree of shapes and set operations.

    Attributes:
        op: ``box`` | ``ellipsoid`` | ``grid`` (a shape) or ``union`` | ``subtract`` | ``intersect`` | ``invert``.
        params: the shape's parameters (world units): box/ellipsoid ``center`` [3], ``half_sizes`` [3],
            ``rotation`` [3,3], ``feather``; grid ``values`` [D,H,W] in [0,1] and ``world_to_grid`` [4,4]
            (world points to the grid's [-1, 1]^3).
        children: the operands of a set operation.
        margin: how far the geometry may grow past the region (world units; None: the feather).
    """

    op: str
    params: dict[str, Any] = field(default_factory=dict)
    children: tuple["Region", ...] = ()
    margin: Optional[float] = None

    # ------------------------------------------------------------------ shapes
    @classmethod
    def box(cls, center: ArrayLike, half_sizes: ArrayLike, rotation: Optional[ArrayLike] = None,
            feather: Optional[float] = None) -> "Region":
        """A box (world units): ``center`` [3], ``half_sizes`` [3] > 0, ``rotation`` (Euler degrees [3] or a
        matrix [3,3]), its edge feathered outward over ``feather``."""
        return cls("box", {"center": _vector(center, "center"), "half_sizes": _vector(half_sizes, "half_sizes", True),
                           "rotation": rotation_matrix(rotation), "feather": _feather(feather)})

    @classmethod
    def ellipsoid(cls, center: ArrayLike, radii: ArrayLike, rotation: Optional[ArrayLike] = None,
                  feather: Optional[float] = None) -> "Region":
        """An ellipsoid (world units): ``center`` [3], ``radii`` [3] > 0, ``rotation`` as :meth:`box`."""
        return cls("ellipsoid", {"center": _vector(center, "center"), "half_sizes": _vector(radii, "radii", True),
                                 "rotation": rotation_matrix(rotation), "feather": _feather(feather)})

    @classmethod
    def grid(cls, values: ArrayLike, world_to_grid: ArrayLike) -> "Region":
        """Values [D,H,W] in [0, 1] on a grid whose [-1, 1]^3 (x: W, y: H, z: D, corners at the corner cells)
        ``world_to_grid`` [4,4] maps world points to."""
        v = np.asarray(values, dtype=np.float32)
        m = np.asarray(world_to_grid, dtype=np.float64)
        if v.ndim != 3 or min(v.shape) < 2 or not np.isfinite(v).all() or v.min() < 0 or v.max() > 1:
            raise ConfigError(f"region grid: values must be [D,H,W] (each >= 2) in [0, 1], got {v.shape}.")
        if m.shape != (4, 4) or not np.isfinite(m).all() or abs(np.linalg.det(m[:3, :3])) < 1e-12:
            raise ConfigError("region grid: world_to_grid must be an invertible [4,4] matrix.")
        return cls("grid", {"values": v, "world_to_grid": m})

    @classmethod
    def from_masks(cls, run: Any, folder: Union[str, Path], **options: Any) -> "Region":
        """The region that the 2D masks in ``folder`` (white = region; any subset of the capture's views, named
        after its images or by view index) select on ``run``'s field (``folder="capture"``: the capture's own
        foreground masks), voted into a grid over the field box by the rendering weights:
        :func:`nerfart_plugin.regions.lift.lift_masks`."""
        values, world_to_grid = lift_masks(run, folder, **options)
        return cls.grid(values, world_to_grid)

    # ------------------------------------------------------------------ set operations
    def __or__(self, other: "Region") -> "Region":
        return self.union(other)

    def __sub__(self, other: "Region") -> "Region":
        return self.subtract(other)

    def __and__(self, other: "Region") -> "Region":
        return self.intersect(other)

    def __invert__(self) -> "Region":
        return self.invert()

    def union(self, *others: "Region") -> "Region":
        """Inside any of them (the largest mask)."""
        return Region("union", children=(self, *others))

    def subtract(self, other: "Region") -> "Region":
        """Inside this and not inside ``other``."""
        return Region("subtract", children=(self, other))

    def intersect(self, *others: "Region") -> "Region":
        """Inside all of them (the smallest mask)."""
        return Region("intersect", children=(self, *others))

    def invert(self) -> "Region":
        """Everywhere but here."""
        return Region("invert", children=(self,))

    def with_margin(self, margin: float) -> "Region":
        """The same region whose geometry may grow ``margin`` world units past it (0: not at all)."""
        if not math.isfinite(float(margin)) or float(margin) < 0:
            raise ConfigError(f"region margin={margin!r}: a distance in world units >= 0.")
        return Region(self.op, self.params, self.children, float(margin))

    # ------------------------------------------------------------------ evaluation
    def mask(self, x: np.ndarray, cell: float) -> np.ndarray:
        """m(x) [N] in [0, 1] at world points x [N,3] (``cell``: the world size of the grid it is sampled on,
        the unit of an automatic feather)."""
        if self.op in ("box", "ellipsoid"):
            p = (np.asarray(x, dtype=np.float64) - self.params["center"]) @ self.params["rotation"]
            h = self.params["half_sizes"]
            d = _box_sdf(p, h) if self.op == "box" else _ellipsoid_sdf(p, h)
            feather = self.params["feather"]
            feather = AUTO_FEATHER_CELLS * cell if feather is None else feather
            if feather <= 0:
                return (d <= 0).astype(np.float32)
            return np.clip(1.0 - d / feather, 0.0, 1.0).astype(np.float32)
        if self.op == "grid":
            return _sample_grid(self.params["values"], self.params["world_to_grid"], x)
        masks = [c.mask(x, cell) for c in self.children]
        if self.op == "union":
            return np.maximum.reduce(masks)
        if self.op == "intersect":
            return np.minimum.reduce(masks)
        if self.op == "subtract":
            return np.minimum(masks[0], 1.0 - masks[1])
        if self.op == "invert":
            return 1.0 - masks[0]
        raise ConfigError(f"region: unknown operation {self.op!r}")

    def feathers(self) -> list[Optional[float]]:
        """The feather of every shape of the region."""
        if self.op in ("box", "ellipsoid"):
            return [self.params["feather"]]
        return [f for c in self.children for f in c.feathers()]

    def bind(self, field_to_world: Any, bound: float, resolution: int = DEFAULT_RESOLUTION,
             world_cell: Optional[float] = None) -> RegionMask:
        """The region sampled on a ``resolution``^3 grid over the field box [-bound, bound]^3, as a
        :class:`~nerfart_plugin.fields.composite.RegionMask` with its geometry mask (dilated by :attr:`margin`).

        Args:
            field_to_world: maps field points [N,3] to world points [N,3] (a run's frame: its normalization, or
                NDC for forward-facing captures).
            world_cell: the world size of one cell (default: measured along the grid's first axis).
        """
        n = int(resolution)
        axis = np.linspace(-bound, bound, n)
        zz, yy, xx = np.meshgrid(axis, axis, axis, indexing="ij")
        pts = np.stack([xx, yy, zz], -1).reshape(-1, 3)
        world = np.asarray(field_to_world(pts), dtype=np.float64)
        if world_cell is None:
            step = world.reshape(n, n, n, 3)
            world_cell = float(np.median(np.linalg.norm(step[:, :, 1:] - step[:, :, :-1], axis=-1)))
        colour = self.mask(world, world_cell).reshape(n, n, n)
        margin = self.margin
        if margin is None:
            known = [f for f in self.feathers() if f is not None]
            margin = max(known) if known else AUTO_FEATHER_CELLS * world_cell
        reach = int(math.ceil(margin / max(world_cell, 1e-12) - 1e-6))
        geometry = torch.from_numpy(colour)[None, None]
        if reach > 0:
            geometry = F.max_pool3d(geometry, kernel_size=2 * reach + 1, stride=1, padding=reach)
        masks = torch.stack([torch.from_numpy(colour), geometry[0, 0]])
        outside = float(self.mask(np.full((1, 3), 1e9), world_cell)[0])
        return RegionMask(masks, bound, outside=outside)

    # ------------------------------------------------------------------ files
    def to_json(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The region as JSON-ready data and the arrays it refers to (grids)."""
        arrays: dict[str, np.ndarray] = {}

        def node(r: Region) -> dict[str, Any]:
            out: dict[str, Any] = {"op": r.op}
            if r.margin is not None:
                out["margin"] = r.margin
            if r.op in ("box", "ellipsoid"):
                out.update(center=r.params["center"].tolist(), half_sizes=r.params["half_sizes"].tolist(),
                           rotation=r.params["rotation"].tolist(), feather=r.params["feather"])
            elif r.op == "grid":
                key = f"grid{len(arrays)}"
                arrays[key] = r.params["values"]
                arrays[key + "_world_to_grid"] = r.params["world_to_grid"]
                out["grid"] = key
            else:
                out["children"] = [node(c) for c in r.children]
            return out

        return {"format": REGION_FORMAT, "region": node(self)}, arrays

    @property
    def content_hash(self) -> str:
        """SHA-256 (16 hex digits) of the region's definition: what names it in a run's cache key."""
        spec, arrays = self.to_json()
        h = hashlib.sha256(json.dumps(spec, sort_keys=True).encode())
        for key in sorted(arrays):
            h.update(key.encode())
            h.update(np.ascontiguousarray(arrays[key]).tobytes())
        return h.hexdigest()[:16]

    def save(self, path: Union[str, os.PathLike]) -> Path:
        """Write the region to ``path`` (``.npz``), atomically."""
        path = Path(path)
        if path.suffix != ".npz":
            raise ConfigError(f"{path}: a region file is a .npz (region.npz).")
        spec, arrays = self.to_json()
        buf = io.BytesIO()
        np.savez_compressed(buf, region=np.frombuffer(json.dumps(spec).encode(), dtype=np.uint8), **arrays)
        with atomic_path(path) as tmp:
            Path(tmp).write_bytes(buf.getvalue())
        return path

    @classmethod
    def load(cls, path: Union[str, os.PathLike]) -> "Region":
        """Read a region file; a file that is not one, or holds a bad value, is a DataError naming the file and
        the field."""
        path = Path(path).expanduser()
        if not path.is_file():
            raise DataError(f"region file {path} does not exist: make one with Region.box(...).save(path), "
                            "`python -m nerfart_plugin.viewer` (Regions panel) or region.box=[...] on the command line.")
        try:
            with np.load(path, allow_pickle=False) as z:
                spec = json.loads(bytes(z["region"]).decode())
                arrays = {k: z[k] for k in z.files if k != "region"}
        except (OSError, ValueError, KeyError, UnicodeDecodeError) as exc:
            raise DataError(f"{path} is not a region file ({type(exc).__name__}: {exc}); write one with "
                            "Region.save(path).") from None
        if not isinstance(spec, dict) or int(spec.get("format", 0)) > REGION_FORMAT:
            raise DataError(f"{path}: region format {spec.get('format') if isinstance(spec, dict) else '?'} is newer "
                            f"than this package reads ({REGION_FORMAT}): upgrade nerfart_plugin.")
        try:
            return _from_node(spec["region"], arrays)
        except (ConfigError, KeyError, TypeError, ValueError) as exc:
            raise DataError(f"{path}: {exc}") from None


def _from_node(node: dict[str, Any], arrays: dict[str, np.ndarray]) -> Region:
    op = node.get("op")
    if op in ("box", "ellipsoid"):
        make = Region.box if op == "box" else Region.ellipsoid
        region = make(node["center"], node["half_sizes"], node.get("rotation"), node.get("feather"))
    elif op == "grid":
        region = Region.grid(arrays[node["grid"]], arrays[node["grid"] + "_world_to_grid"])
    elif op in ("union", "subtract", "intersect", "invert"):
        children = [_from_node(c, arrays) for c in node.get("children", [])]
        need = {"invert": 1, "subtract": 2}.get(op)
        if (need is not None and len(children) != need) or not children:
            raise ConfigError(f"region {op}: {len(children)} operand(s)")
        region = Region(op, children=tuple(children))
    else:
        raise ConfigError(f"region op {op!r}: one of box, ellipsoid, grid, union, subtract, intersect, invert")
    margin = node.get("margin")
    return region.with_margin(margin) if margin is not None else region


def _box_sdf(p: np.ndarray, h: np.ndarray) -> np.ndarray:
    q = np.abs(p) - h
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)


def _ellipsoid_sdf(p: np.ndarray, r: np.ndarray) -> np.ndarray:
    """An ellipsoid's signed distance, approximated (exact on its surface and for spheres)."""
    k0 = np.linalg.norm(p / r, axis=-1)
    k1 = np.linalg.norm(p / (r * r), axis=-1)
    return np.where(k1 > 1e-12, k0 * (k0 - 1.0) / np.maximum(k1, 1e-12), -r.min())


def _sample_grid(values: np.ndarray, world_to_grid: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Trilinear samples [N] of ``values`` [D,H,W] at world points x [N,3] (0 beyond the grid)."""
    x = np.asarray(x, dtype=np.float64)
    g = x @ world_to_grid[:3, :3].T + world_to_grid[:3, 3]
    grid = torch.from_numpy(g.astype(np.float32)).reshape(1, -1, 1, 1, 3)
    vol = torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32))[None, None]
    out = F.grid_sample(vol, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    return out.reshape(-1).numpy().clip(0.0, 1.0)


def region_from_config(rc: Any) -> Optional[Region]:
    """The region a run's ``region`` section asks for (None: the whole scene): its file, box and ellipsoid
    united (each with ``rotation`` and ``feather``), inverted with ``invert``, grown by ``margin``."""
    if not rc.given:
        return None
    parts = []
    if rc.file is not None:
        parts.append(Region.load(rc.file))
    if rc.box is not None:
        parts.append(Region.box(rc.box[:3], rc.box[3:], rc.rotation, rc.feather))
    if rc.ellipsoid is not None:
        parts.append(Region.ellipsoid(rc.ellipsoid[:3], rc.ellipsoid[3:], rc.rotation, rc.feather))
    region = parts[0] if len(parts) == 1 else parts[0].union(*parts[1:])
    if rc.invert:
        region = region.invert()
    return region.with_margin(rc.margin) if rc.margin is not None else region
