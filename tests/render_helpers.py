"""A tiny renderer and one camera view, shared by the two-pass and the CUDA tests."""

from __future__ import annotations

import torch

from nerfart_plugin.data.rays import camera_batch
from nerfart_plugin.systems.base import build_renderer
from nerfart_plugin.systems.scene_setup import SceneSetup


def tiny_renderer(backbone: str, occupancy: int, samples: int = 12, **backbone_kw: object) -> torch.nn.Module:
    """``backbone`` on a 16-cell grid (NeuS: a 4-frequency MLP) in an object setup; ``occupancy``: grid cells
    per side (0: no occupancy grid); ``samples`` per ray; ``backbone_kw``: backbone settings."""
    setup = SceneSetup("object", 1.0, False, [1.0, 1.0, 1.0], False, occupancy, samples, True)
    enc = {"name": "grid", "resolution": 16} if backbone != "neus" else {"name": "frequency", "n_freqs": 4}
    return build_renderer({"name": backbone, **backbone_kw}, enc, {"occupancy": {"warmup_steps": 0}}, setup)


def front_view(H: int, W: int, focal: float) -> dict:
    """The ray batch of a pinhole camera 2.5 units in front of the origin, looking at it."""
    K = torch.tensor([[focal, 0, W / 2], [0, focal, H / 2], [0, 0, 1]])
    c2w = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -2.5]])
    return camera_batch(K, c2w, H, W, 1.0, 4.0, ndc=False)
