"""Small analytic fields with known surfaces that follow the Field contract: the references of the mesh
extraction benchmark (``python -m benchmarks mesh_extraction``) and of the export tests.

They implement only what mesh extraction / comparison needs:
``geometry(x [N,3]) -> [N]``, ``mesh_level``, ``mesh_inside_is_below``, ``signed_distance()``
and ``forward(x [N,3], d [N,3]) -> {"rgb" [N,3] in [0,1], "sdf"|"sigma" [N]}``.
Coordinates are in world units (the field's AABB is [-bound, bound]^3).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from nerfart_plugin.fields.field import Field


def _position_rgb(x: torch.Tensor) -> torch.Tensor:
    """A smooth, position-dependent colour in [0,1]: [N,3] -> [N,3]."""
    return (0.5 + 0.5 * torch.tanh(2.0 * x)).clamp(0.0, 1.0)


class AnalyticSDF(Field):
    """Base of exact signed-distance stand-ins (negative inside, world units)."""

    is_sdf = True
    mesh_level = 0.0
    mesh_inside_is_below = True

    def __init__(self) -> None:
        super().__init__()
        # A buffer so that ``.to(device)`` moves the field and extractors can read its device.
        self.register_buffer("_anchor", torch.zeros(1), persistent=False)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def geometry(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance [N] at points x [N,3]."""
        return self.sdf(x)

    def signed_distance(self):
        return self.sdf

    def forward(self, x: torch.Tensor, d: torch.Tensor) -> dict[str, torch.Tensor]:
        """rgb [N,3] (position colour, slightly view-dependent) and sdf [N]."""
        rgb = _position_rgb(x)
        rgb = (rgb + 0.05 * d.sum(-1, keepdim=True).tanh()).clamp(0.0, 1.0)
        return {"rgb": rgb, "sdf": self.sdf(x)}

    def sample_surface(self, n: int, seed: int = 0) -> np.ndarray:  # pragma: no cover - abstract
        """n points [n,3] uniformly distributed (by area) on the zero level set."""
        raise NotImplementedError


class SphereSDF(AnalyticSDF):
    """Sphere of ``radius`` around ``center``: sdf = |x - c| - r."""

    def __init__(self, radius: float = 0.5, center: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        super().__init__()
        self.radius = float(radius)
        self.register_buffer("center", torch.tensor(center, dtype=torch.float32), persistent=False)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.center.to(x)).norm(dim=-1) - self.radius

    def sample_surface(self, n: int, seed: int = 0) -> np.ndarray:
        v = np.random.default_rng(seed).normal(size=(n, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        return v * self.radius + self.center.cpu().numpy()


class TorusSDF(AnalyticSDF):
    """Torus around the z axis, major radius ``R``, minor radius ``r`` (exact SDF)."""

    def __init__(self, R: float = 0.5, r: float = 0.2) -> None:
        super().__init__()
        self.R, self.r = float(R), float(r)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        q = torch.stack([x[:, :2].norm(dim=-1) - self.R, x[:, 2]], dim=-1)
        return q.norm(dim=-1) - self.r

    def sample_surface(self, n: int, seed: int = 0) -> np.ndarray:
        # Area element is proportional to (R + r cos v): rejection-sample v.
        rng = np.random.default_rng(seed)
        out: list[np.ndarray] = []
        got = 0
        while got < n:
            u = rng.uniform(0, 2 * math.pi, 2 * n)
            v = rng.uniform(0, 2 * math.pi, 2 * n)
            keep = rng.uniform(0, self.R + self.r, 2 * n) < self.R + self.r * np.cos(v)
            u, v = u[keep], v[keep]
            ring = self.R + self.r * np.cos(v)
            out.append(np.stack([ring * np.cos(u), ring * np.sin(u), self.r * np.sin(v)], axis=1))
            got += len(u)
        return np.concatenate(out)[:n]


class UnionSDF(AnalyticSDF):
    """Union (min) of several analytic SDFs, e.g. a body plus a small floating blob."""

    def __init__(self, *parts: AnalyticSDF) -> None:
        super().__init__()
        self.parts = nn.ModuleList(parts)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([p.sdf(x) for p in self.parts], dim=0).amin(dim=0)


class DensityFromSDF(Field):
    """Density-field stand-in: sigma = scale * sigmoid(-sdf / width) (high inside).

    ``mesh_level = scale / 2`` is exactly the zero level set of the wrapped SDF and
    ``mesh_inside_is_below = False`` (inside is where sigma is ABOVE the level).
    """

    is_sdf = False
    mesh_inside_is_below = False

    def __init__(self, base: AnalyticSDF, scale: float = 50.0, width: float = 0.02) -> None:
        super().__init__()
        self.base, self.scale, self.width = base, float(scale), float(width)
        self.mesh_level = self.scale / 2

    def geometry(self, x: torch.Tensor) -> torch.Tensor:
        """Density sigma [N] >= 0 at x [N,3]."""
        return self.scale * torch.sigmoid(-self.base.sdf(x) / self.width)

    def forward(self, x: torch.Tensor, d: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"rgb": _position_rgb(x), "sigma": self.geometry(x)}

    def alpha(self, out: dict[str, torch.Tensor], deltas: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        """``1 - exp(-sigma delta)`` [R,K]: renderable like a NeRF."""
        return -torch.expm1(-out["sigma"].reshape(deltas.shape).float().clamp_min(0) * deltas.float().clamp_min(0))


