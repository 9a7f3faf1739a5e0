"""Camera rays in the OpenCV convention, NeRF's NDC warp, and ray batches.

Conventions (see :mod:`nerfart_plugin.data.scene`): cameras are OpenCV (x right,
y down, z forward); pixel ``(u, v)`` has its centre at ``(u + 0.5, v + 0.5)`` in the
pixel coordinates that ``K`` maps to. A *ray batch* is a dict with ``rays_o`` [R,3],
``rays_d`` [R,3], ``near`` [R], ``far`` [R] and optionally ``rgb`` [R,3],
``mask`` [R], ``view_id`` [R] (long); full-view batches also carry ints ``H``, ``W``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Optional, Sequence

import torch

if TYPE_CHECKING:  # pragma: no cover
    from nerfart_plugin.data.scene import Scene


def pixel_rays(K: torch.Tensor, c2w: torch.Tensor, H: int, W: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through the centres of all pixels of one camera.

    Args:
        K: [3,3] intrinsics in pixels.
        c2w: [3,4] (or [4,4]) camera-to-world, OpenCV convention.
        H, W: image size in pixels.

    Returns:
        origins [H,W,3] (the camera centre repeated) and unit directions [H,W,3]
        in world coordinates; row ``v``, column ``u`` is the ray through pixel
        centre ``(u + 0.5, v + 0.5)``.
    """
    dtype = c2w.dtype if c2w.is_floating_point() else torch.float32
    K = K.to(device=c2w.device, dtype=dtype)
    c2w = c2w.to(dtype)
    v, u = torch.meshgrid(
        torch.arange(H, device=c2w.device, dtype=dtype) + 0.5,
        torch.arange(W, device=c2w.device, dtype=dtype) + 0.5,
        indexing="ij",
    )
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    y = (v - cy) / fy
    x = (u - cx - skew * y) / fx
    dirs_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)  # [H,W,3]
    with torch.autocast(c2w.device.type, enabled=False):  # a bfloat16 rotation tilts rays by ~1 pixel
        dirs = dirs_cam @ c2w[:3, :3].T
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    origins = c2w[:3, 3].expand_as(dirs).clone()
    return origins, dirs


def ndc_rays(
    origins: torch.Tensor,
    dirs: torch.Tensor,
    K: torch.Tensor,
    near_plane: float = 1.0,
    H: Optional[int] = None,
    W: Optional[int] = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """NeRF's normalized-device-coordinate warp for forward-facing scenes.

    Assumes the world frame of a forward-facing scene as produced by the LLFF
    loader: the recentred average camera sits at the origin and looks along
    **-z** (LLFF/NeRF world axes), so scene points have ``z < -near_plane``.
    Origins are first moved onto the plane ``z = -near_plane``; then the scene
    between that plane and infinity maps to the NDC slab ``z_ndc in [-1, 1]``.

    After the warp, the ray ``o_ndc + t * d_ndc`` covers the whole frustum for
    ``t in [0, 1]``: use ``near = 0`` and ``far = 1``. The returned directions are
    **not** unit length (``t`` is not a metric distance).

    Args:
        origins, dirs: [..., 3] world rays (dirs need not be unit).
        K: [3,3] intrinsics of the (shared) camera; ``fx, fy`` are used, and the
            image size defaults to ``W = 2 cx``, ``H = 2 cy``.
        near_plane: depth of the near plane in scene units (1.0 after LLFF's
            ``bd_factor`` scaling).
        H, W: image size, if the principal point is not at the centre.

    Returns:
        (origins_ndc, dirs_ndc), each [..., 3].
    """
    K = K.to(origins)
    fx, fy = K[0, 0], K[1, 1]
    W_ = float(W) if W is not None else 2.0 * K[0, 2]
    H_ = float(H) if H is not None else 2.0 * K[1, 2]
    t = -(near_plane + origins[..., 2]) / dirs[..., 2]
    o = origins + t[..., None] * dirs
    ox, oy, oz = o.unbind(-1)
    dx, dy, dz = dirs.unbind(-1)
    o0 = -2.0 * fx / W_ * ox / oz
    o1 = -2.0 * fy / H_ * oy / oz
    o2 = 1.0 + 2.0 * near_plane / oz
    d0 = -2.0 * fx / W_ * (dx / dz - ox / oz)
    d1 = -2.0 * fy / H_ * (dy / dz - oy / oz)
    d2 = -2.0 * near_plane / oz
    return torch.stack([o0, o1, o2], -1), torch.stack([d0, d1, d2], -1)


def rays_for_views(
    scene: "Scene",
    ids: Sequence[int],
    ndc: bool = False,
    with_rgb: bool = True,
    background: Optional[Sequence[float]] = None,
) -> dict:
    """All rays of the views ``ids`` as one flat ray batch.

    Args:
        scene: the loaded scene.
        ids: view indices.
        ndc: apply :func:`ndc_rays` (forward-facing scenes only); then
            ``near = 0`` and ``far = 1``.
        with_rgb: include ``rgb`` (and ``mask`` when the scene has masks).
        background: if given and the scene has masks, composite the target
            ``rgb * mask + background * (1 - mask)``.

    Returns:
        a ray batch dict with R = len(ids) * H * W rays, row-major per view; if a
        single view is requested, also ints ``H`` and ``W``.
    """
    H, W = scene.height, scene.width
    outs_o, outs_d, nears, fars, vids, rgbs, masks = [], [], [], [], [], [], []
    for i in ids:
        o, d = pixel_rays(scene.K[i], scene.c2w[i], H, W)
        o, d = o.reshape(-1, 3), d.reshape(-1, 3)
        n = o.shape[0]
        if ndc:
            o, d = ndc_rays(o, d, scene.K[i], near_plane=1.0, H=H, W=W)
            nears.append(torch.zeros(n))
            fars.append(torch.ones(n))
        else:
            nears.append(torch.full((n,), float(scene.near[i])))
            fars.append(torch.full((n,), float(scene.far[i])))
        outs_o.append(o)
        outs_d.append(d)
        vids.append(torch.full((n,), int(i), dtype=torch.long))
        if with_rgb:
            rgb = scene.images[i].reshape(-1, 3).float()
            if scene.masks is not None:
                m = scene.masks[i].reshape(-1).float()
                masks.append(m)
                if background is not None:
                    bg = torch.as_tensor(background, dtype=rgb.dtype)
                    rgb = rgb * m[:, None] + bg * (1.0 - m[:, None])
            rgbs.append(rgb)
    batch: dict = {
        "rays_o": torch.cat(outs_o).float(),
        "rays_d": torch.cat(outs_d).float(),
        "near": torch.cat(nears).float(),
        "far": torch.cat(fars).float(),
        "view_id": torch.cat(vids),
    }
    if with_rgb:
        batch["rgb"] = torch.cat(rgbs)
        if masks:
            batch["mask"] = torch.cat(masks)
    if len(ids) == 1:
        batch["H"], batch["W"] = int(H), int(W)
    return batch


def camera_batch(K: torch.Tensor, c2w: torch.Tensor, H: int, W: int, near: float, far: float,
                 ndc: bool) -> dict:
    """Ray batch of one camera (intrinsics ``K`` [3,3] already at H x W, ``c2w`` [3,4]): ``rays_o`` /
    ``rays_d`` [H*W,3], ``near`` / ``far`` [H*W] (NDC: 0 and 1), plus ints ``H``, ``W``."""
    o, d = pixel_rays(K, c2w, H, W)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    n = o.shape[0]
    if ndc:
        o, d = ndc_rays(o, d, K, 1.0, H=H, W=W)
        near, far = 0.0, 1.0
    return {"rays_o": o.float(), "rays_d": d.float(), "near": torch.full((n,), float(near)),
            "far": torch.full((n,), float(far)), "H": int(H), "W": int(W)}


def views_at_resolution(scene: "Scene", ids: Sequence[int], resolution: int, ndc: bool) -> list[dict]:
    """Ray batches (:func:`camera_batch`, plus ``view_id``) of the views ``ids`` with the long side resized
    to ``resolution`` pixels (the stylization views)."""
    s = resolution / max(scene.height, scene.width)
    H, W = max(1, round(scene.height * s)), max(1, round(scene.width * s))
    views = []
    for i in ids:
        K = scene.K[i].clone()
        K[0] *= W / scene.width
        K[1] *= H / scene.height
        b = camera_batch(K, scene.c2w[i], H, W, float(scene.near[i]), float(scene.far[i]), ndc)
        b["view_id"] = int(i)
        views.append(b)
    return views
