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

#: the smallest image side (pixels) a capture can be reconstructed from (SSIM's 11 px window fits inside)
MIN_IMAGE_SIDE = 12
#: what a capture must satisfy to be reconstructed, checked by :meth:`Scene.validate` when any loader returns it
RECONSTRUCTABLE = (
    f"images at least {MIN_IMAGE_SIDE} px on each side (after data.resolution)",
    "at least 2 views, at least 1 of them for training",
    "masks, where a capture has them, not all empty",
    "cameras at more than one position (a baseline)",
    "for object and unbounded captures: at least half of the cameras facing the scene's centre",
    "finite camera parameters, far > near for every camera, one name, pose and intrinsics per image",
)


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
        """Check the contract and what a capture must satisfy to be reconstructed (the list in
        :data:`RECONSTRUCTABLE`); raise DataError naming ``source`` and every problem found."""

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
        if not problems:
            problems = self.reconstructable_problems()
        if problems:
            raise DataError(f"Invalid scene from {self.source}: " + "; ".join(problems))
        return self

    def reconstructable_problems(self) -> list[str]:
        """What keeps this capture from being reconstructed (:data:`RECONSTRUCTABLE`), each with its fix."""
        n, h, w, _ = self.images.shape
        out = []
        if min(h, w) < MIN_IMAGE_SIDE:
            out.append(f"the images are {w}x{h} px; at least {MIN_IMAGE_SIDE} px a side are needed (data.resolution "
                       "or larger photos)")
        if n < 2 or not self.train_ids:
            out.append(f"{n} view(s) with {len(self.train_ids)} for training: a reconstruction needs at least 2 views")
        if self.masks is not None and float(self.masks.amax()) <= 0.0:
            out.append("every mask is empty (an alpha channel or matte that is 0 everywhere): fix the mattes, or "
                       "remove them to reconstruct without masks")
        centres = self.c2w[:, :3, 3]
        if n >= 2 and float(torch.cdist(centres, centres).max()) <= 1e-6 * max(1.0, float(centres.norm(dim=-1).max())):
            out.append("every camera sits at the same place: without a baseline nothing can be triangulated; "
                       "capture from several positions")
        if self.capture != "forward_facing" and n >= 2:
            # the object lies around the origin of the normalized frame: the cameras must face it
            to_centre = -centres
            forward = self.c2w[:, :3, 2]
            facing = (torch.nn.functional.cosine_similarity(forward, to_centre, dim=-1) > 0.0).float().mean()
            if float(facing) < 0.5:
                out.append(f"only {float(facing):.0%} of the cameras face the scene's centre: the poses look away "
                           "from the object (a flipped axis convention? check the poses' camera convention)")
        return out
