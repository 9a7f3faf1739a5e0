"""MLP building blocks of the fields: plain MLPs, the geometric-init SDF MLP (a sphere at start) and a
sharp softplus whose backward is cheap."""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn as nn
from torch import Tensor


class _SharpSoftplusFn(torch.autograd.Function):
    """``softplus_beta(x) = (relu(beta x) + log(1 + exp(-|beta x|))) / beta``; gradient ``sigmoid(beta x)``.

    The same function as ``F.softplus(x, beta)`` (to 6e-8 absolute in float32: for ``|beta x| > 17``
    ``log(1 + e)`` rounds to 0 where log1p would give ``e < 4e-8``), computed with ``log`` instead of
    ``log1p``, whose CPU kernel is several times slower than ``exp`` and ``log``. Its backward is one
    sigmoid instead of softplus_backward's exp, and is itself differentiable (the analytic eikonal
    gradient takes the double backward), since it is written in differentiable ops of the saved input.
    """

    @staticmethod
    def forward(ctx: Any, x: Tensor, beta: float) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(x)
        ctx.beta = beta
        z = x * beta
        return (torch.relu(z) + torch.log(1.0 + torch.exp(-z.abs()))) / beta

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        (x,) = ctx.saved_tensors
        return grad * torch.sigmoid(x * ctx.beta), None


class SharpSoftplus(nn.Module):
    """``nn.Softplus(beta)`` (no threshold: exact everywhere), about 2x faster forward and backward on a
    CPU (:class:`_SharpSoftplusFn`). x [...] -> [...], same dtype."""

    def __init__(self, beta: float = 100.0) -> None:
        super().__init__()
        self.beta = float(beta)

    def forward(self, x: Tensor) -> Tensor:
        if torch.compiler.is_compiling():  # the compiler fuses the plain ops, forward and backward, into one loop
            z = x * self.beta
            return (torch.relu(z) + torch.log(1.0 + torch.exp(-z.abs()))) / self.beta
        return _SharpSoftplusFn.apply(x, self.beta)

    def extra_repr(self) -> str:
        return f"beta={self.beta}"


def make_mlp(in_dim: int, hidden_dim: int, out_dim: int, n_hidden_layers: int, act: type[nn.Module] = nn.ReLU) -> nn.Sequential:
    """``n_hidden_layers`` Linear+act layers of width ``hidden_dim``, then a Linear to ``out_dim``."""
    layers: list[nn.Module] = []
    d = in_dim
    for _ in range(max(0, n_hidden_layers)):
        layers += [nn.Linear(d, hidden_dim), act()]
        d = hidden_dim
    layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


class GeometricInitMLP(nn.Module):
    """SDF MLP with the geometric initialisation of SAL/IDR (Atzmon & Lipman 2020).

    Input is ``[x, extra]`` with x [N,3] raw world coordinates and ``extra``
    [N,E] encoding features. At init the first layer only sees x (weights on
    ``extra`` are zero, so any encoding can be attached without breaking the
    init), hidden weights are N(0, 2/width), and the last layer's SDF row is
    N(sqrt(pi)/sqrt(width), 1e-4) with bias ``-radius``: the network starts as
    (approximately) the SDF of a sphere of ``radius``, ``sdf(x) ~ |x| - radius``.
    Activation: softplus with beta=100 (smooth, so the eikonal gradient is
    well defined). Output [N, 1 + feature_dim]: sdf then geometry features.

    With small widths (64) the random init is only a rough sphere (mean error
    ~0.35 radius), so by default (``refine_init``) the SDF output row is then
    re-fitted by ridge least squares to ``|x| - radius`` on 8192 fixed points
    in [-2 radius, 2 radius]^3 (mean error ~0.02 radius, eikonal ~ satisfied).
    """

    def __init__(self, extra_dim: int, hidden_dim: int, n_hidden_layers: int, feature_dim: int, radius: float,
                 refine_init: bool = True) -> None:
        super().__init__()
        dims = [3 + extra_dim] + [hidden_dim] * max(1, n_hidden_layers)
        self.hidden = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.out = nn.Linear(dims[-1], 1 + feature_dim)
        self.act = SharpSoftplus(beta=100.0)
        with torch.no_grad():
            for i, lin in enumerate(self.hidden):
                nn.init.normal_(lin.weight, 0.0, math.sqrt(2.0) / math.sqrt(lin.out_features))
                nn.init.zeros_(lin.bias)
                if i == 0 and extra_dim > 0:
                    lin.weight[:, 3:].zero_()
            nn.init.normal_(self.out.weight, 0.0, 1e-2)
            nn.init.zeros_(self.out.bias)
            nn.init.normal_(self.out.weight[:1], math.sqrt(math.pi) / math.sqrt(dims[-1]), 1e-4)
            self.out.bias[:1].fill_(-float(radius))
            if refine_init:
                self._refine_sphere(float(radius), extra_dim)

    @torch.no_grad()
    def _refine_sphere(self, radius: float, extra_dim: int) -> None:
        gen = torch.Generator().manual_seed(0)
        x = (torch.rand(8192, 3, generator=gen) * 2.0 - 1.0) * 2.0 * radius
        h = torch.cat([x, torch.zeros(x.shape[0], extra_dim)], -1).to(self.out.weight.device)
        for lin in self.hidden:
            h = self.act(lin(h))
        A = torch.cat([h, torch.ones_like(h[:, :1])], -1)
        y = x.norm(dim=-1, keepdim=True).to(A.device) - radius
        eye = torch.eye(A.shape[1], device=A.device)
        sol = torch.linalg.solve(A.T @ A + 1e-4 * eye, A.T @ y)[:, 0]
        if torch.isfinite(sol).all():
            self.out.weight[0] = sol[:-1]
            self.out.bias[0] = sol[-1]

    def forward(self, h: Tensor) -> Tensor:
        for lin in self.hidden:
            h = self.act(lin(h))
        return self.out(h)
