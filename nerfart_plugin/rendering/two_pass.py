"""Memory-saving exact backprop through a full rendered view (NeRF-Art Section 4.4).

CLIP and VGG need the whole view, but rendering a whole view with grad keeps
every sample's activations alive. Instead:

1. render the full view without grad, in chunks, with stratified jitter fixed
   for this step (the returned ``t_samples`` record the samples);
2. compute the image losses on that image and their gradient ``dL/dI`` [R,3];
3. re-render the rays patch by patch *with* grad at exactly the same samples
   and back-propagate ``sum(rgb_patch * dL/dI_patch)`` (plus any per-ray loss
   such as the weight regularization of Eq. 7, scaled by the patch's share of
   rays), accumulating parameter gradients.

Since the image is a sum of independent per-ray renders, the accumulated
gradient equals that of full backprop (up to float summation order).

Where memory allows, :func:`render_with_graph` and :func:`backprop_retained` trade
memory for time (``stylize.backprop=retain``): pass 1 marches the view *with*
grad and keeps its graph, pass 3 back-propagates through it, and the re-render of
pass 3 is saved. Same samples, same gradient (up to float summation order); the
graph holds every evaluated sample of the view.
"""

from __future__ import annotations

from typing import Any, Callable, Optional

import torch
from torch import Tensor

from nerfart_plugin.rendering.renderer import VolumeRenderer

#: ``fn(render_out, rays) -> per-patch mean loss``: the patch's render and its ray batch (which carries
#: any per-ray targets of the full view, sliced with it, e.g. ``source_opacity``)
RayLoss = Callable[[dict[str, Tensor], dict[str, Any]], Tensor]


def slice_rays(batch: dict[str, Any], idx: slice, n: int) -> dict[str, Any]:
    """Rows ``idx`` of every per-ray tensor (first dim ``n``) of a ray batch; other entries as they are."""
    return {k: (v[idx] if torch.is_tensor(v) and v.dim() > 0 and v.shape[0] == n else v) for k, v in batch.items()}


@torch.no_grad()
def render_fixed_samples(renderer: VolumeRenderer, batch: dict[str, Any], chunk: int, perturb: bool = True,
                         generator: Optional[torch.Generator] = None) -> dict[str, Tensor]:
    """Pass 1: render all rays of ``batch`` without grad; returns ``rgb`` [R,3], ``depth`` [R],
    ``opacity`` [R] and the ``t_samples`` [R,K,2] to reuse in pass 2.

    Rays are marched with early termination (:meth:`VolumeRenderer.march`): the sections behind a
    ray's stop get zero length in ``t_samples``, so pass 2 re-renders the same pixels without
    evaluating them (their weights, and so their gradients, are below ``stop_transmittance``)."""
    n = batch["rays_o"].shape[0]
    keys = ("rgb", "depth", "opacity", "t_samples")
    parts: dict[str, list[Tensor]] = {k: [] for k in keys}
    for s in range(0, n, chunk):
        out = renderer.march(slice_rays(batch, slice(s, s + chunk), n), perturb=perturb, generator=generator,
                             with_normals=False)  # colour only: SDF fields skip the gradient taps
        for k in keys:
            parts[k].append(out[k])
    return {k: torch.cat(v, 0) for k, v in parts.items()}


def backprop_patches(renderer: VolumeRenderer, batch: dict[str, Any], t_samples: Tensor, rgb_grad: Tensor,
                     patch_rays: int, ray_losses: Optional[dict[str, tuple[float, RayLoss]]] = None,
                     backward: Callable[[Tensor], None] = torch.autograd.backward) -> dict[str, float]:
    """Pass 3: re-render ``batch`` in patches of ``patch_rays`` rays with grad and back-propagate.

    Args:
        renderer: the renderer being optimized.
        batch: the full-view ray batch used in pass 1.
        t_samples: [R,K,2] from :func:`render_fixed_samples` (identical samples).
        rgb_grad: [R,3] gradient of the image losses w.r.t. the rendered colours.
        patch_rays: rays per re-rendered patch (memory knob).
        ray_losses: optional ``name -> (lambda, fn(render_out, rays) -> per-patch mean loss)``,
            e.g. Eq. 7; each is weighted by the patch's share of rays so the total
            equals the mean over all rays.
        backward: how to back-propagate a scalar (``LightningModule.manual_backward`` in training). It is
            called with autocast off: Lightning runs ``training_step`` under ``trainer.precision``'s autocast,
            and a backward inside an autocast casts the backward matmuls of float32 forward ops (the SDF
            geometry net, kept float32 on purpose) to bfloat16/float16 as well; outside it every backward op
            runs in its forward op's dtype (PyTorch AMP notes: backward under autocast is not recommended).

    Returns:
        the value of each ray loss (mean over all rays), for logging.
    """
    n = batch["rays_o"].shape[0]
    ray_losses, totals = _active(ray_losses)
    for s in range(0, n, patch_rays):
        sl = slice(s, s + patch_rays)
        sub = slice_rays(batch, sl, n)
        out = renderer(sub, perturb=False, t_samples=t_samples[sl])
        surrogate = _surrogate(out, sub, rgb_grad[sl], n, ray_losses, totals)
        with torch.autocast(surrogate.device.type, enabled=False):
            backward(surrogate)
    return totals


def render_with_graph(renderer: VolumeRenderer, batch: dict[str, Any], chunk: int, perturb: bool = True,
                      generator: Optional[torch.Generator] = None) -> tuple[dict[str, Tensor], list[dict[str, Tensor]]]:
    """Pass 1, keeping the graph (``stylize.backprop=retain``): march all rays of ``batch`` with grad,
    ``chunk`` rays at a time (:meth:`VolumeRenderer.march_with_grad`, normals and regularizers included
    as in pass 3).

    Returns ``(first, chunks)``: ``first`` as :func:`render_fixed_samples` returns it (detached ``rgb``
    [R,3], ``depth`` [R], ``opacity`` [R], ``t_samples`` [R,K,2]); ``chunks`` the renders with their
    graphs, for :func:`backprop_retained`.
    """
    n = batch["rays_o"].shape[0]
    chunks = [renderer.march_with_grad(slice_rays(batch, slice(s, s + chunk), n), perturb=perturb,
                                       generator=generator) for s in range(0, n, chunk)]
    first = {k: torch.cat([c[k].detach() for c in chunks], 0) for k in ("rgb", "depth", "opacity", "t_samples")}
    return first, chunks


def backprop_retained(chunks: list[dict[str, Tensor]], batch: dict[str, Any], rgb_grad: Tensor,
                      ray_losses: Optional[dict[str, tuple[float, RayLoss]]] = None,
                      backward: Callable[[Tensor], None] = torch.autograd.backward) -> dict[str, float]:
    """Pass 3 through the graphs :func:`render_with_graph` kept: one backward of ``sum(rgb * dL/dI)``
    plus the ray losses, each chunk's weighted by its share of rays (as :func:`backprop_patches`).

    Args:
        chunks: the renders of :func:`render_with_graph`, in ray order.
        batch: the full-view ray batch they rendered (per-ray targets of the ray losses).
        rgb_grad, ray_losses, backward: as for :func:`backprop_patches` (the backward runs with autocast off).

    Returns:
        the value of each ray loss (mean over all rays), for logging.
    """
    n = batch["rays_o"].shape[0]
    ray_losses, totals = _active(ray_losses)
    surrogate, s = None, 0
    for out in chunks:
        sl = slice(s, s + out["rgb"].shape[0])
        term = _surrogate(out, slice_rays(batch, sl, n), rgb_grad[sl], n, ray_losses, totals)
        surrogate = term if surrogate is None else surrogate + term
        s = sl.stop
    if s != n:
        raise ValueError(f"the retained chunks render {s} rays, the batch has {n}: pass the batch they rendered")
    with torch.autocast(surrogate.device.type, enabled=False):
        backward(surrogate)
    return totals


def _active(ray_losses: Optional[dict[str, tuple[float, RayLoss]]]) -> tuple[dict[str, tuple[float, RayLoss]],
                                                                          dict[str, float]]:
    """The ray losses with a non-zero λ, and their running totals (0)."""
    active = {k: v for k, v in (ray_losses or {}).items() if v[0] != 0.0}
    return active, {k: 0.0 for k in active}


def _surrogate(out: dict[str, Tensor], rays: dict[str, Any], rgb_grad: Tensor, n: int,
               ray_losses: dict[str, tuple[float, RayLoss]], totals: dict[str, float]) -> Tensor:
    """``sum(rgb * dL/dI)`` of one patch plus its ray losses weighted by its share of the ``n`` rays;
    adds each loss's share to ``totals``."""
    share = out["rgb"].shape[0] / n
    surrogate = (out["rgb"] * rgb_grad).sum()
    for name, (lam, fn) in ray_losses.items():
        value = fn(out, rays)
        totals[name] += float(value.detach()) * share
        surrogate = surrogate + lam * share * value
    return surrogate
