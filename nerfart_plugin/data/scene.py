"""The scene contract every loader returns and everything downstream reads.

Conventions
-----------
* Cameras are OpenCV: x right, y down, z forward (looking along +z).
* ``c2w`` maps camera coordinates to the *normalized* world frame.
* ``normalization`` is the 4x4 similarity ``T`` with ``x_normalized = T @ x_original``
  (homogeneous), so original-world points can be mapped into the scene frame.
* For ``capture == "object"`` (and ``"unbounded"``) the region of interest lies
  inside the unit sphere of the normalized frame. For ``"forward_facing"``
  (LLFF) the scene is rendered in NDC (see :mod:`nerfart_plugin.data.rays`),
  and ``near``/``far`` are the scene bounds before the NDC warp.
* ``near``/``far`` are distances along unit-length ray directions.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

import torch

from nerfart_plugin.errors import DataError

CaptureType = Literal["object", "forward_facing", "unbounded"]


@dataclass
class Scene:
    """A posed image set.

    Attributes:
        images: float32 [N,H,W,3] in [0,1].
        masks: float32 [N,H,W] in [0,1] (1 = foreground) or None.
        c2w: float32 [N,3,4] camera-to-world, OpenCV convention, normalized frame.
        K: float32 [N,3,3] pinhole intrinsics in pixels for the returned resolution.
        near: float32 [N] near distance per camera (normalized units).
        far: float32 [N] far distance per camera (normalized units).
        image_names: N file names (no folder; data=nerfstudio: the path relative to the scene folder).
        train_ids: indices used for training.
        val_ids: held-out indices (every ``holdout_every``-th view by default).
        normalization: float32 [4,4] similarity, ``x_norm = T @ x_orig``.
        capture: how the scene was captured; decides the field extent and
            whether a background model is needed.
        source: the folder or file the scene was loaded from.
        notes: human-readable notes on what the loader did about quirks
            (skipped files, count mismatches, rescaled intrinsics), also logged.
        content_hash: SHA-256 of the input files that define the scene, used to
            key cached reconstructions.
    """

    images: torch.Tensor
    masks: Optional[torch.Tensor]
    c2w: torch.Tensor
    K: torch.Tensor
    near: torch.Tensor
    far: torch.Tensor
    image_names: list[str]
    train_ids: list[int]
    val_ids: list[int]
    normalization: torch.Tensor
    capture: CaptureType
    source: Path
    notes: list[str] = field(default_factory=list)
    content_hash: str = ""

    @property
    def num_images(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def validate(self) -> "Scene":
        """Check shapes and value ranges; raise DataError naming ``source`` on failure."""

        n, h, w, c = self.images.shape
        problems = []
        if c != 3:
            problems.append(f"images have {c} channels, expected 3")
        if self.masks is not None and tuple(self.masks.shape) != (n, h, w):
            problems.append(f"masks shape {tuple(self.masks.shape)} != {(n, h, w)}")
        if tuple(self.c2w.shape) != (n, 3, 4):
            problems.append(f"c2w shape {tuple(self.c2w.shape)} != {(n, 3, 4)}")
        if tuple(self.K.shape) != (n, 3, 3):
            problems.append(f"K shape {tuple(self.K.shape)} != {(n, 3, 3)}")
        if len(self.image_names) != n:
            problems.append(f"{len(self.image_names)} names for {n} images")
        if not torch.isfinite(self.c2w).all() or not torch.isfinite(self.K).all():
            problems.append("non-finite camera parameters")
        if (self.far <= self.near).any():
            problems.append("far <= near for some camera")
        if problems:
            raise DataError(f"Invalid scene from {self.source}: " + "; ".join(problems))
        return self
