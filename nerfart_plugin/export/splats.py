"""A field as 3D Gaussian splats: fitted to the field's own renders, written as the standard 3DGS ``.ply``.

The conversion is a fit, not a point dump (:func:`fit_splats`):

1. **Initialization** on the field's surface: ``count`` points spread evenly over its marching-cubes surface (the
   SDF's zero level, a density field's ``mesh_level``), each a flat Gaussian lying in the surface (two axes the
   local point spacing, the third a tenth of it), its colour the field's seen from outside, opacity 0.9.
2. **Optimization** of every Gaussian's position, scale, rotation, opacity and colour (Adam, the 3DGS rates)
   against the field's renders from many cameras: the capture's training views and an orbit, rendered once at
   ``resolution`` px; each step renders a random share of one view's tiles
   (:func:`~nerfart_plugin.rendering.splats.rasterize_tiles`; with gsplat on CUDA, the whole view) and takes the
   L1 error.
3. **Quality**: PSNR and SSIM of the splats against the field on the capture's held-out views.

The file (:func:`write_ply`, with ``plyfile``) holds ``x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2
rot_0..3``, float32, binary little-endian: opacity as a logit, scales as logs, the rotation a unit quaternion w
first, colour the degree-0 SH coefficient, ``f_rest`` zeros (no view dependence), normals zeros. Its frame is
``export.frame``'s, as the meshes': ``world`` (the capture's own) or ``normalized``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from plyfile import PlyData, PlyElement
from torch import Tensor
from tqdm.auto import tqdm

from nerfart_plugin.data.rays import camera_batch
from nerfart_plugin.errors import DataError
from nerfart_plugin.export.mesh import MeshExtractor
from nerfart_plugin.objectives.losses import psnr
from nerfart_plugin.rendering.splats import (C0, Splats, gsplat_available, quat_to_rotmat, rasterize,
                                             rasterize_gsplat, rasterize_tiles, rotmat_to_quat, tile_pixels)
from nerfart_plugin.utils.clock import PartClock
from nerfart_plugin.utils.io import atomic_path

log = logging.getLogger("nerfart_plugin")

#: the properties of a 3DGS .ply vertex, in the order viewers read them
PLY_PROPERTIES = (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
                  + [f"f_rest_{i}" for i in range(45)] + ["opacity"] + [f"scale_{i}" for i in range(3)]
                  + [f"rot_{i}" for i in range(4)])


@dataclass(frozen=True)
class SplatFit:
    """How a field is fitted as splats (``export.splat_*``).

    Attributes:
        count: Gaussians; steps: optimizer steps; resolution: long side (px) of the field's renders fitted to;
        orbit_views: orbit cameras besides the capture's training views; tile_share: share of a view's tiles
        rendered per step; seed: of the initialization and the order of views.
    """

    count: int = 10000
    steps: int = 500
    resolution: int = 128
    orbit_views: int = 24
    tile_share: float = 0.25
    seed: int = 0
    lr: dict[str, float] = field(default_factory=lambda: {"means": 1.6e-4, "quats": 1e-3, "log_scales": 5e-3,
                                                          "opacities": 5e-2, "colours": 2.5e-3})


# ---------------------------------------------------------------------- initialization
@torch.no_grad()
def initial_splats(field_: Any, count: int, seed: int = 0, mesh_resolution: int = 128) -> Splats:
    """``count`` flat Gaussians spread evenly over ``field_``'s surface (see the module docstring)."""
    mesh = MeshExtractor(resolution=mesh_resolution, bound=float(field_.bound)).extract(field_)
    points, faces = trimesh.sample.sample_surface_even(mesh, count, seed=seed)
    if len(points) < count:  # sample_surface_even may return fewer: top up uniformly
        extra, extra_faces = trimesh.sample.sample_surface(mesh, count - len(points), seed=seed + 1)
        points, faces = np.concatenate([points, extra]), np.concatenate([faces, extra_faces])
    normals = np.asarray(mesh.face_normals)[faces]
    spacing = math.sqrt(float(mesh.area) / count)
    device = next(iter(field_.parameters()), torch.zeros(0)).device
    n = torch.as_tensor(normals, dtype=torch.float32)
    helper = torch.where((n[:, :1].abs() < 0.9), torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0]))
    t1 = F.normalize(torch.cross(n, helper, dim=-1), dim=-1)
    t2 = torch.cross(n, t1, dim=-1)
    R = torch.stack([t1, t2, n], -1)  # columns: the Gaussian's axes
    p = torch.as_tensor(points, dtype=torch.float32)
    rgb = field_colour(field_, p.to(device), n.to(device)).cpu()
    scales = torch.tensor([spacing, spacing, 0.1 * spacing]).log().expand(len(p), 3).clone()
    opacity = torch.full((len(p),), math.log(0.9 / 0.1))
    return Splats(p, rotmat_to_quat(R), scales, opacity, (rgb - 0.5) / C0)


def field_colour(field_: Any, points: Tensor, normals: Tensor, chunk: int = 65536) -> Tensor:
    """[N,3] the field's colour at surface points, seen from outside along the normal."""
    out = []
    for s in range(0, len(points), chunk):
        o = field_.query(points[s:s + chunk], -normals[s:s + chunk], with_normal=False)
        out.append(o["rgb"].float().clamp(0, 1))
    return torch.cat(out)


# ---------------------------------------------------------------------- the field's views
@dataclass
class Views:
    """Cameras and the field's renders of them: ``c2w`` [V,3,4], ``K`` [V,3,3] at H x W, ``rgb`` [V,H,W,3]."""

    c2w: Tensor
    K: Tensor
    H: int
    W: int
    rgb: Tensor


@torch.no_grad()
def field_views(run: Any, ids: Any, orbit: int, resolution: int) -> Views:
    """The run's renders of capture views ``ids`` and ``orbit`` orbit cameras at ``resolution`` px (long side)."""
    cams = run.cameras
    paths = [run.camera(int(i), resolution) for i in ids]
    if orbit > 0:
        paths.append(run.camera_path("orbit", orbit, resolution))
    c2w = torch.cat([p.c2w for p in paths]).float()
    K = torch.cat([p.K for p in paths]).float()
    H, W = paths[0].height, paths[0].width
    near, far = float(cams.near.min()), float(cams.far.max())
    images = []
    for i in tqdm(range(len(c2w)), desc="rendering the field for the splats", leave=False):
        b = camera_batch(K[i], c2w[i], H, W, near, far, cams.ndc)
        b = {k: v.to(run.device) if torch.is_tensor(v) else v for k, v in b.items()}
        out = run.renderer.render_chunked(b, chunk=run.config.render.chunk, with_normals=False)
        images.append(out["rgb"].reshape(H, W, 3).clamp(0, 1).cpu())
    return Views(c2w, K, H, W, torch.stack(images))


# ---------------------------------------------------------------------- the fit
def render_splats(splats: Splats, c2w: Tensor, K: Tensor, H: int, W: int,
                  background: Optional[Tensor] = None) -> dict[str, Tensor]:
    """The splats from one camera: gsplat on CUDA where it is installed, else the PyTorch rasterizer."""
    if gsplat_available(splats.means.device):
        return rasterize_gsplat(splats, c2w, K, H, W, background)
    return rasterize(splats, c2w, K, H, W, background)


def fit_splats(splats: Splats, views: Views, cfg: SplatFit, background: Tensor,
               device: torch.device = torch.device("cpu")) -> tuple[Splats, list[float]]:
    """Optimize ``splats`` to reproduce ``views`` (see the module docstring); returns them and the loss curve."""
    params = [t.detach().clone().to(device).requires_grad_(True) for t in splats.parameters()]
    fitted = Splats(*params)
    names = ("means", "quats", "log_scales", "opacities", "colours")
    extent = float(views.c2w[:, :3, 3].norm(dim=-1).mean())
    groups = [{"params": [p], "lr": cfg.lr[n] * (extent if n == "means" else 1.0), "name": n}
              for n, p in zip(names, params)]
    opt = torch.optim.Adam(groups, eps=1e-15)
    g = torch.Generator().manual_seed(cfg.seed)
    pixels = tile_pixels(views.H, views.W)
    n_tiles = pixels.shape[0]
    per_step = max(1, int(round(cfg.tile_share * n_tiles)))
    target = views.rgb.reshape(len(views.rgb), -1, 3)
    background = background.to(device)
    curve = []
    means_lr0 = groups[0]["lr"]
    gsplat = gsplat_available(device)
    for step in tqdm(range(cfg.steps), desc="fitting splats", leave=False):
        v = int(torch.randint(len(views.c2w), (1,), generator=g))
        tiles = torch.randperm(n_tiles, generator=g)[:per_step]
        loss = _step_loss(fitted, views, v, tiles, pixels, target, background, gsplat)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        groups[0]["lr"] = means_lr0 * (0.01 ** (step / max(1, cfg.steps - 1)))  # 3DGS: the positions' rate decays
        curve.append(float(loss.detach()))
    return fitted.detach(), curve


def _step_loss(splats: Splats, views: Views, v: int, tiles: Tensor, pixels: Tensor, target: Tensor,
               background: Tensor, gsplat: bool) -> Tensor:
    """The L1 error of one step: gsplat renders view ``v`` whole; the PyTorch rasterizer only ``tiles``."""
    device = splats.means.device
    if gsplat:
        img = rasterize_gsplat(splats, views.c2w[v], views.K[v], views.H, views.W, background)["rgb"]
        return (img.reshape(-1, 3) - target[v].to(device)).abs().mean()
    out = rasterize_tiles(splats, views.c2w[v], views.K[v], views.H, views.W, tiles, background)
    pix = pixels[tiles]
    valid = (pix >= 0).to(device)
    want = target[v][pix.clamp_min(0)].to(device)
    return ((out["rgb"] - want).abs() * valid[..., None]).sum() / (3 * valid.sum().clamp_min(1))


@torch.no_grad()
def splat_quality(splats: Splats, views: Views, background: Tensor) -> dict[str, float]:
    """PSNR (dB) and SSIM of the splats' renders against the field's on ``views``."""
    from kornia.metrics import ssim

    ps, ss = [], []
    for i in range(len(views.c2w)):
        img = render_splats(splats, views.c2w[i], views.K[i], views.H, views.W, background)["rgb"].cpu().clamp(0, 1)
        ps.append(float(psnr(img, views.rgb[i])))
        ss.append(float(ssim(img.permute(2, 0, 1)[None], views.rgb[i].permute(2, 0, 1)[None], 11).mean()))
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "views": len(ps)}


# ---------------------------------------------------------------------- frames and files
def to_world(splats: Splats, normalization: np.ndarray) -> Splats:
    """Splats of the normalized frame in the capture's world frame (``x_norm = T x_world``, T a similarity):
    positions mapped, scales divided by T's scale, rotations turned by its rotation."""
    T = torch.as_tensor(np.asarray(normalization, dtype=np.float64))
    Ti = torch.linalg.inv(T)
    scale = float(torch.linalg.det(Ti[:3, :3]).abs() ** (1.0 / 3.0))
    R = (Ti[:3, :3] / scale).float()
    means = splats.means.double() @ Ti[:3, :3].T + Ti[:3, 3]
    rot = rotmat_to_quat(R @ quat_to_rotmat(splats.quats))
    return Splats(means.float(), rot, splats.log_scales + math.log(scale), splats.opacities.clone(),
                  splats.colours.clone())


def write_ply(splats: Splats, path: Path) -> Path:
    """The 3DGS ``.ply`` (see the module docstring), atomically; refuses non-finite values."""
    s = splats.detach()
    cols = {
        "x": s.means[:, 0], "y": s.means[:, 1], "z": s.means[:, 2],
        "opacity": s.opacities, **{f"f_dc_{i}": s.colours[:, i] for i in range(3)},
        **{f"scale_{i}": s.log_scales[:, i] for i in range(3)},
        **{f"rot_{i}": F.normalize(s.quats, dim=-1)[:, i] for i in range(4)},
    }
    data = np.zeros(len(s), dtype=[(name, "<f4") for name in PLY_PROPERTIES])
    for name, values in cols.items():
        data[name] = values.cpu().numpy().astype(np.float32)
    if not all(np.isfinite(data[name]).all() for name in PLY_PROPERTIES):
        raise DataError(f"{path}: the splats hold non-finite values; nothing was written.")
    with atomic_path(Path(path)) as tmp:
        PlyData([PlyElement.describe(data, "vertex")], text=False, byte_order="<").write(str(tmp))
    return Path(path)


def read_ply(path: Path) -> Splats:
    """A 3DGS ``.ply`` back as splats (f_rest ignored)."""
    try:
        v = PlyData.read(str(path))["vertex"]
        get = lambda *names: torch.as_tensor(np.stack([np.asarray(v[n], dtype=np.float32) for n in names], -1))  # noqa: E731
        return Splats(get("x", "y", "z"), get("rot_0", "rot_1", "rot_2", "rot_3"),
                      get("scale_0", "scale_1", "scale_2"), get("opacity")[:, 0], get("f_dc_0", "f_dc_1", "f_dc_2"))
    except (OSError, KeyError, ValueError) as exc:
        raise DataError(f"{path} is not a 3DGS splat .ply ({type(exc).__name__}: {exc}).") from None


def export_splats(run: Any, path: Path, cfg: SplatFit, frame: str = "world") -> dict[str, Any]:
    """Fit ``run``'s field (any Run: a blend, a region) as splats and write them to ``path``: what was fitted and
    how well (PSNR / SSIM against the field on the capture's held-out views), for ``metrics.json``."""
    clock = PartClock()
    torch.manual_seed(cfg.seed)
    field_ = run.renderer.field
    with clock.part("initialization"):
        splats = initial_splats(field_, cfg.count, cfg.seed)
    ids = run.cameras.train_ids or list(range(len(run.cameras.c2w)))
    held = [i for i in range(len(run.cameras.c2w)) if i not in set(ids)] or ids[:4]
    with clock.part("field renders"):
        views = field_views(run, ids, cfg.orbit_views, cfg.resolution)
        held_views = field_views(run, held, 0, cfg.resolution)
    background = field_background(run)
    with clock.part("quality"):
        start = splat_quality(splats, held_views, background)
    with clock.part("fit"):
        fitted, curve = fit_splats(splats, views, cfg, background, torch.device(run.device))
    with clock.part("quality"):
        quality = splat_quality(fitted, held_views, background)
    out = to_world(fitted.to("cpu"), run.cameras.normalization) if frame == "world" else fitted.to("cpu")
    write_ply(out, path)
    seconds = clock.total()
    log.info("splats: %d Gaussians fitted in %d steps (%.0f s): %.2f dB / SSIM %.3f against the field on %d "
             "held-out views (%.2f dB at the surface initialization) -> %s", len(fitted), cfg.steps, seconds,
             quality["psnr"], quality["ssim"], quality["views"], start["psnr"], path)
    return {"file": str(path), "gaussians": len(fitted), "steps": cfg.steps, "resolution": cfg.resolution,
            "frame": frame, "psnr": quality["psnr"], "ssim": quality["ssim"], "psnr_initial": start["psnr"],
            "ssim_initial": start["ssim"], "views": quality["views"], "seconds": round(seconds, 1),
            "seconds_by_part": {k: round(v, 1) for k, v in clock.seconds.items()},
            "bytes": Path(path).stat().st_size, "final_loss": curve[-1] if curve else None}


def field_background(run: Any) -> Tensor:
    """[3] the colour behind the field's renders (white when it has none)."""
    colour = run.renderer.background_color
    return torch.ones(3) if colour is None else torch.as_tensor(colour, dtype=torch.float32).reshape(3)
