"""Peak memory and time of full backprop versus patch backprop (NeRF-Art Section 4.4).

One stylization-like step on a reconstruction-sized field (the default config:
``backbone=volsdf encoding=grid``, 64 samples/ray, 64^3 occupancy grid; change
with ``--override``), for a square view of S x S pixels (S = 64, 128, 256, 512):

* **full**: sample the rays, render the whole view *with* grad, image loss, backward;
* **patch**: :func:`~nerfart_plugin.rendering.two_pass.render_fixed_samples` (no grad,
  ``render.chunk`` rays at a time), image loss and dL/dI, then
  :func:`~nerfart_plugin.rendering.two_pass.backprop_patches` with patches of
  ``stylize.patch_size``^2 rays.

The image loss is a fixed differentiable function of the whole image standing in
for CLIP + VGG: the toy guidance's absolute loss (Eq. 3) + 2 x the toy edge
perceptual loss (Eq. 9) to a fixed grey image, plus 0.1 x the weight
regularization (Eq. 7) per ray. Both methods use identical samples, so their
parameter gradients must agree: the table gives the max relative difference.

Each (method, size) runs in a fresh subprocess; memory = the child's peak RSS
(VmHWM, reset after setup: field built, warm-up done) minus its RSS at that
moment, or ``torch.cuda.max_memory_allocated`` on CUDA. A child's address
space is capped at setup + ``--mem-cap`` GiB and its run time at ``--timeout`` s;
sizes predicted (linearly in the number of rays) to exceed either are skipped.

    python -m benchmarks patch_backprop                 # 64 128 256 512
    python -m benchmarks patch_backprop --quick         # smoke run, scratch output
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common

log = logging.getLogger("bench.patch_backprop")
NAME = "patch_backprop"
LAMBDA_REG = 0.1
QUICK_OVERRIDES = ["render.num_samples=16", "render.occupancy.resolution=16", "stylize.patch_size=16",
                   "render.chunk=512"]


# --------------------------------------------------------------------------- child: one measurement
def camera_view(size: int) -> dict[str, Any]:
    """A square S x S view of the unit box from 2.5 units away (the head scene's framing)."""
    import torch

    from nerfart_plugin.data.rays import camera_batch

    f = 1.15 * size
    K = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    c2w = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -2.5]])
    return camera_batch(K, c2w, size, size, 1.0, 4.0, ndc=False)


def image_loss_fn(size: int, device):
    """Fixed differentiable image loss: toy Eq. 3 + 2 x toy Eq. 9 to a grey image. ``rgb`` [S*S,3] -> scalar."""
    import torch

    from nerfart_plugin.guidance import EdgePerceptual, ToyGuidance
    from nerfart_plugin.objectives.losses import absolute_clip_loss, perceptual_loss

    g, perc = ToyGuidance().to(device), EdgePerceptual().to(device)
    txt = g.encode_text(["a painting in vivid blue and gold"])
    with torch.no_grad():
        target = [f.detach() for f in perc.features(torch.full((1, 3, size, size), 0.5, device=device))]

    def loss(rgb):
        img = rgb.reshape(size, size, 3).permute(2, 0, 1)[None]
        return absolute_clip_loss(g.encode_image(img), txt) + 2.0 * perceptual_loss(perc.features(img), target)

    return loss


def _chunks(n: int, size: int):
    return [slice(s, s + size) for s in range(0, n, size)]


def run_method(r, view: dict, mode: str, chunk: int, patch_rays: int, loss_fn, seed: int) -> None:
    import torch

    from nerfart_plugin.objectives.losses import weight_regularization
    from nerfart_plugin.rendering.two_pass import backprop_patches, render_fixed_samples, slice_rays

    g = torch.Generator().manual_seed(seed)
    n = view["rays_o"].shape[0]
    if mode == "full":
        with torch.no_grad():  # the same chunked draws as render_fixed_samples -> identical samples
            ts = torch.cat([r.sample(slice_rays(view, sl, n), True, g) for sl in _chunks(n, chunk)])
        out = r(view, perturb=False, t_samples=ts)
        loss = loss_fn(out["rgb"]) + LAMBDA_REG * weight_regularization(out["weights"], out["t"])
        loss.backward()
    else:
        first = render_fixed_samples(r, view, chunk, perturb=True, generator=g)
        img = first["rgb"].clone().requires_grad_(True)
        grad = torch.autograd.grad(loss_fn(img), img)[0]
        backprop_patches(r, view, first["t_samples"], grad, patch_rays,
                         {"reg": (LAMBDA_REG, lambda o, _: weight_regularization(o["weights"], o["t"]))})


def measure(payload: dict[str, Any]) -> dict[str, Any]:
    """Child: build the field, warm up, then time one ``mode`` step at ``size`` and report peak memory."""
    import torch

    from nerfart_plugin.config.validate import parse_config
    from nerfart_plugin.data.setup import SceneSetup
    from nerfart_plugin.systems.base import build_renderer
    from nerfart_plugin.utils.device import pick_device, to_device

    c, _ = parse_config(common.compose(["stage=reconstruct", *payload["overrides"]]))
    device = pick_device(c.device)
    torch.manual_seed(0)
    rc = c.render
    occ = rc.occupancy.resolution if rc.occupancy.enabled is not False else 0
    setup = SceneSetup("object", 1.0, False, rc.background_color, False, occ, rc.num_samples, True)
    r = build_renderer(c, setup).to(device)
    r.update_occupancy(0, force=True)
    size, mode = int(payload["size"]), payload["mode"]
    chunk, patch_rays = rc.chunk, c.stylize.patch_size ** 2
    # warm-up at 8x8 (lazy kernel/allocator initialisation is not part of the measurement)
    run_method(r, to_device(camera_view(8), device), mode, chunk, patch_rays, image_loss_fn(8, device), 1)
    view = to_device(camera_view(size), device)
    loss_fn = image_loss_fn(size, device)
    r.zero_grad(set_to_none=True)
    gc.collect()
    base = common.reset_peak_rss()
    if device.type == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats(device)
        cuda_base = torch.cuda.memory_allocated(device)
    else:
        common.limit_memory(float(payload["mem_cap_gib"]) * common.GiB)
    t0 = time.perf_counter()
    run_method(r, view, mode, chunk, patch_rays, loss_fn, 7)
    if device.type == "cuda":
        torch.cuda.synchronize()
    secs = time.perf_counter() - t0
    if device.type == "cuda":
        peak = torch.cuda.max_memory_allocated(device) - cuda_base
        how = "cuda max_memory_allocated"
    else:
        peak = common.peak_rss() - base
        how = "peak RSS"
    grads = {n: p.grad.detach().cpu() for n, p in r.named_parameters() if p.grad is not None}
    torch.save(grads, payload["grad_path"])
    return {"seconds": secs, "peak_bytes": int(peak), "baseline_rss": int(base), "how": how,
            "samples": int(view["rays_o"].shape[0]) * rc.num_samples}


def max_rel_diff(a: dict, b: dict) -> float:
    worst = 0.0
    for n, ga in a.items():
        gb = b.get(n)
        if gb is None:
            return float("inf")
        worst = max(worst, float((ga - gb).abs().max() / ga.abs().max().clamp_min(1e-12)))
    return worst


# --------------------------------------------------------------------------- parent
def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["--child"]:
        return common.child_main(measure, argv[1])
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=None, help="view sides in px (default 64 128 256 512)")
    p.add_argument("--mem-cap", type=float, default=8.0, help="GiB above setup allowed per child (default 8)")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds allowed per child (default 1800)")
    p.add_argument("--override", nargs="*", default=[], help="extra Hydra overrides (e.g. backbone=neus)")
    common.add_common_args(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sizes = args.sizes or ([16, 32] if args.quick else [64, 128, 256, 512])
    overrides = list(args.override) + (QUICK_OVERRIDES if args.quick else [])
    info = common.machine_info()
    c = common.compose(["stage=reconstruct", *overrides])
    rows, raw = [], []
    last: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for size in sorted(sizes):
            res: dict[str, dict] = {}
            for mode in ("full", "patch"):
                prev = last.get(mode)
                skip = None
                if prev is not None:
                    k = size**2 / prev["size"] ** 2
                    if prev["peak_bytes"] * k > args.mem_cap * common.GiB:
                        skip = f"skipped (predicted {prev['peak_bytes'] * k / common.GiB:.1f} GiB > {args.mem_cap:g} GiB)"
                    elif prev["seconds"] * k > args.timeout:
                        skip = f"skipped (predicted {prev['seconds'] * k:.0f} s > {args.timeout:g} s)"
                if skip:
                    res[mode] = {"status": "skipped", "note": skip}
                    log.info("%d px %s: %s", size, mode, skip)
                    continue
                payload = {"size": size, "mode": mode, "overrides": overrides, "mem_cap_gib": args.mem_cap,
                           "grad_path": str(Path(tmp) / f"{mode}_{size}.pt")}
                out = common.run_child(Path(__file__), payload, args.timeout)
                if out["status"] == "timeout":
                    out["note"] = f"skipped (> {args.timeout:g} s)"
                elif out["status"] == "oom":
                    out["note"] = f"skipped (> {args.mem_cap:g} GiB)"
                elif out["status"] == "ok":
                    last[mode] = {**out, "size": size}
                else:
                    out["note"] = "error: " + out.get("error", "?")[:120]
                res[mode] = out
                log.info("%d px %s: %s", size, mode, {k: v for k, v in out.items() if k != "error"})
            diff = None
            if all(res[m]["status"] == "ok" for m in ("full", "patch")):
                import torch

                diff = max_rel_diff(torch.load(Path(tmp) / f"full_{size}.pt", weights_only=True),
                                    torch.load(Path(tmp) / f"patch_{size}.pt", weights_only=True))
            raw.append({"size": size, **res, "max_rel_grad_diff": diff})
            cell = lambda m, k, f: (f(res[m][k]) if res[m]["status"] == "ok" else res[m].get("note", res[m]["status"]))
            mib = lambda b: f"{b / 2**20:.0f}"
            ratio = (f"{res['full']['peak_bytes'] / max(res['patch']['peak_bytes'], 1):.1f}x"
                     if res["full"]["status"] == "ok" and res["patch"]["status"] == "ok" else "–")
            rows.append([f"{size}x{size}", size * size, cell("full", "seconds", lambda v: f"{v:.2f}"),
                         cell("full", "peak_bytes", mib), cell("patch", "seconds", lambda v: f"{v:.2f}"),
                         cell("patch", "peak_bytes", mib), ratio, common.fmt(diff, ".1e")])
    how = next((r[m]["how"] for r in raw for m in ("full", "patch") if r[m].get("status") == "ok"), "peak RSS")
    patch = int(c["stylize"]["patch_size"])
    body = [
        f"Field: backbone={c['backbone']['name']}, encoding={c['encoding']['name']}, "
        f"{c['render']['num_samples']} samples/ray, occupancy grid {c['render']['occupancy']['resolution']}^3 "
        f"(untrained field: cost does not depend on the weights, every ray gets K samples). "
        f"Patch backprop: pass 1 in chunks of {c['render']['chunk']} rays, patches of {patch}x{patch} = {patch * patch} rays. "
        "Loss: toy absolute CLIP (Eq. 3) + 2 x toy edge perceptual (Eq. 9) on the whole image + 0.1 x Eq. 7 per ray. "
        f"Memory: {how} above the child's RSS after setup and warm-up (peak mark reset there; MiB); each configuration in a fresh process. "
        f"Caps: {args.mem_cap:g} GiB, {args.timeout:g} s per configuration.",
        "",
    ]
    body += common.md_table(["view", "rays", "full: time (s)", "full: peak mem (MiB)", "patch: time (s)",
                             "patch: peak mem (MiB)", "memory full/patch", "max rel. grad diff"], rows, "lrrrrrrr")
    ok = [r["max_rel_grad_diff"] for r in raw if r["max_rel_grad_diff"] is not None]
    if ok:
        body += ["", f"Gradients: patch backprop matches full backprop to a max relative difference of "
                     f"{max(ok):.1e} (float32 summation order) — {'OK' if max(ok) < 1e-3 else 'MISMATCH'}."]
    raw_path = common.raw_path(NAME, args.quick)
    raw_path.parent.mkdir(parents=True, exist_ok=True)
    raw_path.write_text(json.dumps(raw, indent=1, default=str))
    text = common.section(NAME, "Patch backprop versus full backprop: peak memory and time",
                          common.command(NAME + ".py", argv), info, body, args.quick)
    common.finish(args, NAME, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
