"""The paper's resolution at interactive cost: one stylization step versus its guidance floor, and the whole job.

Part 1, one step at the paper's resolution (256x256 on the shipped head, 270x480 on the
selfie ``fangzhou_nature``; ``stylize.resolution=auto``, the paper's 12 local patches of
1/10 of the view's area): the project's stylization system on the preset's trained reconstruction,
driven by Lightning for ``--steps`` steps (first dropped; the one-off source render of a
view excluded), with the real networks' cost: open_clip ViT-B/32 + VGG16 with RANDOM
weights (the architecture a user runs; the weights cannot be downloaded here) and
``guidance=imagenet`` (EfficientNet-Lite0, real ImageNet weights). The **floor** is what
the guidance alone costs per step, measured in the same run: forward+backward of the view
and its local patches through ``encode_images``, exactly as the step calls it (on a CPU
this cost grows with the number of images, so no rendering speed can go below it).
Goal (issue 12): step <= 1.3x the floor.

Part 2, the whole paper-resolution job on ``fangzhou_nature`` as a user runs it
(``preset=paper_res``: frames at 270x480, the preset's one-level reconstruction, then 4 epochs of the
training views at 270x480 with 12 local patches), ``guidance=imagenet``, from an empty
output root: wall time of each stage, held-out PSNR, the judge. Goal: <= 45 min on the
2-core development machine. :func:`paper_job` is also the GPU benchmark's job (``gpu.py``).

    python -m benchmarks paper_resolution
    python -m benchmarks paper_resolution --skip-job                  # part 1 only
    python -m benchmarks paper_resolution --quick
    python -m benchmarks paper_resolution --skip-steps --skip-job     # the section from the raw file only
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Optional

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common

log = logging.getLogger("bench.paper_resolution")
NAME = "paper_resolution"
PROMPT = "brain coral"
TARGET_RATIO, TARGET_JOB_S = 1.3, 45 * 60.0
SCENES: dict[str, list[str]] = {
    "head": ["data=h3ds"],
    "fangzhou_nature": ["data=h3ds", "data.path={shared}/fangzhou_nature"],
}
GUIDES: dict[str, list[str]] = {
    "clip (random weights)": ["guidance=clip", "guidance.allow_random_weights=true", "guidance.allow_download=false",
                              "guidance.pretrained=null", "guidance.perceptual.weights=null"],
    "imagenet": ["guidance=imagenet"],
}
#: Lightning mixed precisions part 1 also times, with this guide (the method's own networks)
MIXED, MIXED_GUIDE = ("bf16-mixed", "16-mixed"), "clip (random weights)"
#: ``stylize.backprop`` modes part 1 also times (float32, the same guide) against the paper's patches
BACKPROPS = ("retain",)
QUICK = ["data.resolution=48", "reconstruct.steps=200", "reconstruct.val_every=1000", "render.occupancy.resolution=16",
         "export.enabled=false"]


# --------------------------------------------------------------------------- part 1
def step_cost(scene_overrides: list[str], guide: str, steps: int, reps: int, out_root: Path,
              quick: bool, precision: str = "32-true", backprop: str = "patch") -> dict[str, Any]:
    """Median step and its parts, and the guidance floor of the same step, at the scene's own resolution,
    under ``trainer.precision=precision`` and ``stylize.backprop=backprop``."""
    import torch

    from benchmarks.stylization import Context, run_steps, steady, timed
    from nerfart_plugin.guidance import random_patches

    ctx = Context([*scene_overrides, "preset=paper_res", f"output_root={out_root}", *(QUICK if quick else [])], None,
                  "trained")  # the preset's reconstruction: its field is what the preset stylizes
    ov = [*GUIDES[guide], "stylize.resolution=auto", "stylize.video_frames=0",  # the preset is in ctx.base
          f"trainer.precision={precision}", f"stylize.backprop={backprop}"]
    r = run_steps(ctx, ov, steps, prompt=PROMPT)
    s = steady(r["timings"])
    g, k = r["guidance"], int(r["local_patches"])
    view = ctx.scene.views(ctx.scene.scene.train_ids[:1], r["resolution"])[0]
    H, W = int(view["H"]), int(view["W"])
    frac = float(ctx.c["stylize"]["local_patch_frac"])
    gen = torch.Generator().manual_seed(0)

    def floor_passes(encode_images: Any) -> Any:
        def run() -> None:
            img = torch.rand(1, 3, H, W, requires_grad=True)
            emb = encode_images([img, random_patches(img, k, frac, g.input_size, generator=gen)])
            sum(e.float().mean() for e in emb).backward()
        return run

    guidance_passes = floor_passes(g.encode_images)
    floor = timed(guidance_passes, reps)
    log.info("%s at %dx%d: step %.2f s, guidance floor %.2f s (view + %d patches), ratio %.2f", guide, W, H,
             s["step_no_cache"], floor, k, s["step_no_cache"] / floor)
    out = {"guide": guide, "precision": precision, "backprop_mode": backprop, "width": W, "height": H, "local_patches": k,
           "samples": r["num_samples"], "step": s["step_no_cache"], "render": s["render_nograd"],
           "losses": s["losses_and_image_grad"], "backprop": s["patch_backprop"], "floor": floor,
           "ratio": s["step_no_cache"] / floor, "steps": len(r["timings"])}
    if backprop != "patch":
        return {**out, **retained_graph_cost(ctx, view, r["num_samples"], int(ctx.c["stylize"]["chunk"]),
                                             int(ctx.c["stylize"]["patch_size"]) ** 2)}
    if precision == "32-true":
        return {**out, **precision_costs(g, r["perceptual"], guidance_passes, H, W, reps),
                **({"floor_open_clip": timed(floor_passes(open_clip_as_loaded(g)), reps)} if g.name == "clip" else {})}
    return {**out, **mixed_fidelity(ctx, view, r["num_samples"], precision)}


def retained_graph_cost(ctx: Any, view: dict[str, Any], samples: int, chunk: int, patch_rays: int) -> dict[str, Any]:
    """What ``stylize.backprop=retain`` keeps and changes on the source field's ``view``: the bytes autograd
    saves for the backward (the whole view's graph, against one patch of ``patch_rays`` rays, the most the
    paper's backprop holds at once), and the cosine of the parameter gradients of both ways for a fixed
    random image gradient, same samples (the ray terms aside)."""
    import torch

    from nerfart_plugin.rendering.two_pass import (backprop_patches, backprop_retained, render_fixed_samples,
        render_with_graph)

    r, img_grad = source_field_and_image_gradient(ctx, view, samples)

    def grads() -> torch.Tensor:
        out = torch.cat([p.grad.flatten() for p in r.parameters() if p.grad is not None])
        r.zero_grad(set_to_none=True)
        return out

    first = render_fixed_samples(r, view, chunk, generator=torch.Generator().manual_seed(1))
    with SavedBytes() as per_patch:

        def backward(loss: torch.Tensor) -> None:
            per_patch.close_graph()  # this patch's graph is complete: count the next one afresh
            loss.backward()

        backprop_patches(r, view, first["t_samples"], img_grad, patch_rays, backward=backward)
    g_patch = grads()
    with SavedBytes() as whole_view:
        _, chunks = render_with_graph(r, view, chunk, generator=torch.Generator().manual_seed(1))
        whole_view.close_graph()
    backprop_retained(chunks, view, img_grad)
    g_kept = grads()
    return {"graph_patch_mib": max(per_patch.graphs) / 2**20, "graph_view_mib": whole_view.graphs[0] / 2**20,
            "grad_cos": float(torch.nn.functional.cosine_similarity(g_kept, g_patch, dim=0))}


class SavedBytes:
    """Context counting the bytes of the distinct storages autograd saves for backward passes: one total per
    graph in ``graphs`` (:meth:`close_graph` ends one), parameters included."""

    def __init__(self) -> None:
        import torch

        self.graphs: list[int] = []
        self._seen: set[int] = set()
        self._bytes = 0
        self._hooks = torch.autograd.graph.saved_tensors_hooks(self._pack, lambda x: x)

    def _pack(self, x: Any) -> Any:
        storage = x.untyped_storage()
        if storage.data_ptr() not in self._seen:
            self._seen.add(storage.data_ptr())
            self._bytes += storage.nbytes()
        return x

    def close_graph(self) -> None:
        self.graphs.append(self._bytes)
        self._seen, self._bytes = set(), 0

    def __enter__(self) -> "SavedBytes":
        self._hooks.__enter__()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._hooks.__exit__(*exc)


def source_field_and_image_gradient(ctx: Any, view: dict[str, Any], samples: int) -> tuple[Any, Any]:
    """The source field's renderer at ``samples`` per ray, and a fixed random image gradient [R,3] for ``view``."""
    import torch

    from nerfart_plugin.systems.base import build_renderer

    r = build_renderer(ctx.scene.cfg, ctx.scene.setup)
    r.load_state_dict(ctx.source_state)
    r.num_samples = samples
    return r, torch.randn(view["rays_o"].shape[0], 3, generator=torch.Generator().manual_seed(0)) * 1e-3


def mixed_fidelity(ctx: Any, view: dict[str, Any], samples: int, precision: str) -> dict[str, Any]:
    """What ``trainer.precision`` (a ``*-mixed`` one) changes in the source field's render of ``view`` and in
    the field's parameter gradient of one two-pass backprop (a fixed random image gradient): PSNR (dB) and
    cosine against float32, same samples."""
    import torch

    from nerfart_plugin.objectives.losses import psnr
    from nerfart_plugin.rendering.two_pass import backprop_patches, render_fixed_samples

    dtype = torch.bfloat16 if precision.startswith("bf16") else torch.float16
    r, img_grad = source_field_and_image_gradient(ctx, view, samples)

    def render_and_grad(mixed: bool) -> tuple[torch.Tensor, torch.Tensor]:
        r.zero_grad(set_to_none=True)
        with torch.autocast(view["rays_o"].device.type, dtype=dtype, enabled=mixed):
            first = render_fixed_samples(r, view, 8192, generator=torch.Generator().manual_seed(1))
            backprop_patches(r, view, first["t_samples"], img_grad, 8192)
        return first["rgb"].float(), torch.cat([p.grad.flatten() for p in r.parameters() if p.grad is not None])

    (ref, g_ref), (low, g_low) = render_and_grad(False), render_and_grad(True)
    return {"render_db": float(psnr(low.clamp(0, 1), ref.clamp(0, 1))),
            "grad_cos": float(torch.nn.functional.cosine_similarity(g_low, g_ref, dim=0))}


def open_clip_as_loaded(g: Any) -> Any:
    """``encode_images`` of the CLIP guidance ``g`` through a plain open_clip copy of its network, as the
    guidance ran it before 2026-12-05: float32 weights that autocast casts on every call, the strided
    convolution as patch embedding, torch's default attention kernel; the same preprocessing, precision
    and one image at a time on CPU."""
    import copy

    import torch

    net = copy.deepcopy(g.net)
    emb = net.visual.conv1
    net.visual.conv1 = torch.nn.Conv2d(emb.in_channels, emb.out_channels, emb.kernel_size, stride=emb.stride,
                                       bias=emb.bias is not None)
    net.visual.conv1.weight, net.visual.conv1.bias = emb.weight, emb.bias
    dtype = g.compute_dtype(torch.device("cpu"))

    def encode_images(imgs: list[torch.Tensor]) -> list[torch.Tensor]:
        x = torch.cat([g.preprocess(i) for i in imgs])
        with torch.autocast("cpu", dtype=dtype, enabled=dtype != torch.float32):
            emb = torch.cat([net.encode_image(xi[None]) for xi in x]) if dtype != torch.float32 else net.encode_image(x)
        return list(emb.float().split([i.shape[0] for i in imgs]))

    return encode_images


def precision_costs(guidance: Any, perceptual: Any, guidance_passes: Any, H: int, W: int, reps: int) -> dict[str, Any]:
    """The guidance floor and the perceptual network's forward+backward at the view's size, in the precision
    ``auto`` picks on this machine and in float32 (the floor's images batched in one pass), same run:
    which arithmetic is faster on this CPU. Only for networks with a ``precision`` setting (CLIP, VGG16)."""
    import torch

    from benchmarks.stylization import fwd_bwd, timed

    out: dict[str, Any] = {}
    for key, net, fn in (("floor", guidance, guidance_passes),
                         ("perceptual", perceptual, fwd_bwd(getattr(perceptual, "features", None), (1, 3, H, W)))):
        if not hasattr(net, "precision"):
            continue
        auto = net.precision
        out[f"{key}_dtype"] = str(net.compute_dtype(torch.device("cpu"))).replace("torch.", "")
        if key == "perceptual":
            out["perceptual_auto"] = timed(fn, reps)
        net.precision = "fp32"
        try:
            out[f"{key}_fp32"] = timed(fn, reps)
        finally:
            net.precision = auto
    return out


# --------------------------------------------------------------------------- part 2
def _timed_run(overrides: list[str], device: str) -> tuple[dict[str, Any], float, float]:
    """(results, wall seconds, peak accelerator GiB or 0) of one pipeline run."""
    import torch

    from nerfart_plugin.run.pipeline import run

    cuda = device.startswith("cuda")
    if cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    res = run(common.compose(overrides))
    if cuda:
        torch.cuda.synchronize()
    return res, time.perf_counter() - t0, torch.cuda.max_memory_allocated() / 2**30 if cuda else 0.0


def paper_job(data_root: Path, out: Path, device: str, quick: bool, prompt: str = PROMPT) -> dict[str, Any]:
    """The paper-resolution job on fangzhou_nature (``preset=paper_res``, ``guidance=imagenet``) in ``out``:
    seconds of each stage (as a user waits for them: training, evaluation, video, meshes), PSNR, judge."""
    base = ["data=h3ds", f"data.path={data_root / 'fangzhou_nature'}", "preset=paper_res", "guidance=imagenet",
            f"prompt={json.dumps(prompt)}", f"device={device}", f"output_root={out}", "export.texture=false"]
    if quick:
        base += ["reconstruct.steps=200", "stylize.epochs=null", "stylize.steps=4", "stylize.video_frames=2", "export.resolution=64",
                 "data.resolution=64"]
    rec, rec_s, rec_mem = _timed_run([*base, "stage=reconstruct"], device)
    sty, sty_s, sty_mem = _timed_run([*base, "stage=stylize"], device)
    metrics = json.loads((Path(sty["stylization"]["dir"]) / "metrics.json").read_text())
    judge = metrics.get("judge") or {}
    steps = max(1, int(metrics.get("steps") or 1))
    return {"reconstruct_s": rec_s, "stylize_s": sty_s, "job_s": rec_s + sty_s, "psnr": rec["reconstruction"].get("psnr"),
            "steps": steps, "step_s": (metrics.get("train_seconds_this_process") or sty_s) / steps,
            "top5_source": judge.get("source", {}).get("top5_rate"), "top5": judge.get("stylized", {}).get("top5_rate"),
            "prompt": prompt, "peak_gib": max(rec_mem, sty_mem)}


# --------------------------------------------------------------------------- report
def _measured_by(raw: dict[str, Any], part: str) -> list[str]:
    """The line naming the run that measured ``part`` (parts may come from different runs of this script)."""
    run = raw.get("measured_by", {}).get(part)
    return [f"Measured by `{run['command']}` ({run['utc']}).", ""] if run else []


def _precision_label(row: dict[str, Any]) -> str:
    """`` / bf16-mixed`` for a row under a trainer precision other than float32 (`` / retain`` for a
    ``stylize.backprop`` other than the paper's patches), else empty."""
    precision, backprop = row.get("precision", "32-true"), row.get("backprop_mode", "patch")
    return ("" if precision == "32-true" else f" / {precision}") + ("" if backprop == "patch" else f" / {backprop}")


def _is_baseline(row: dict[str, Any]) -> bool:
    """float32 and the paper's patch backprop: the row the others are compared with."""
    return row.get("precision", "32-true") == "32-true" and row.get("backprop_mode", "patch") == "patch"


def _headroom(rows: list[dict[str, Any]]) -> list[str]:
    """What the goal leaves besides the guidance passes, against what the field work alone measured and
    against the two passes every step runs whatever its backprop (pass 1 and the perceptual network)."""
    f = common.fmt
    lines = [f"- {r['scene']} / {r['guide']}{_precision_label(r)}: at {TARGET_RATIO}x the rest of the step (both "
             f"render passes, the perceptual network, the loss arithmetic) would have to fit in {f(_allowance(r))} s; "
             f"the field work alone (pass 1 + pass 2) took {f(r['render'] + r['backprop'])} s "
             f"({f((r['render'] + r['backprop']) / r['floor'])}x the floor), the losses beyond the floor "
             f"{f(max(0.0, r['losses'] - r['floor']))} s.{_unavoidable(r)}" for r in rows if r.get("floor")]
    return ["", "What the goal leaves (same figures):", "", *lines] if lines else []


def _allowance(row: dict[str, Any]) -> float:
    """Seconds the goal leaves a step besides its guidance floor."""
    return row["floor"] * (TARGET_RATIO - 1)


def _unavoidable(row: dict[str, Any]) -> str:
    """What a patch-backprop step runs whatever its backprop costs: the no-grad render, plus the perceptual
    network's forward+backward where the row timed it. Their sum over the goal's allowance puts the goal out
    of reach at this field's cost per sample. Empty for other backprop modes (their pass 1 keeps a graph)."""
    if row.get("backprop_mode", "patch") != "patch":
        return ""
    f = common.fmt
    parts = [("the no-grad render", row["render"])]
    if row.get("perceptual_auto") is not None:
        parts.append(("the perceptual network", row["perceptual_auto"]))
    total = sum(seconds for _, seconds in parts)
    verdict = "more than the allowance" if total > _allowance(row) else "within the allowance"
    named = " and ".join(f"{name} ({f(seconds)} s)" for name, seconds in parts)
    return f" What every step runs whatever its backprop costs, {named}, takes {f(total)} s: {verdict}."


def _versus_baseline(rows: list[dict[str, Any]], marker: str, setting: str,
                     extra: Any) -> list[list[str]]:
    """Table rows for the part-1 rows that carry ``marker``, against the float32 patch row of the same scene
    and guide: scene, guide, the row's ``setting``, step and field-work speed-ups, then ``extra(row)``."""
    f = common.fmt
    base = {(r["scene"], r["guide"]): r for r in rows if _is_baseline(r)}
    out = []
    for r in rows:
        ref = base.get((r["scene"], r["guide"]))
        if marker in r and ref is not None:
            out.append([r["scene"], r["guide"], r[setting], f(ref["step"] / r["step"]),
                        f((ref["render"] + ref["backprop"]) / (r["render"] + r["backprop"])), *extra(r)])
    return out


def _mixed(rows: list[dict[str, Any]]) -> list[str]:
    """Mixed-precision rows against the float32 row of the same scene and guide: time and fidelity."""
    f = common.fmt
    out = _versus_baseline(rows, "render_db", "precision", lambda r: [f(r["render_db"], ".1f"), f(r["grad_cos"], ".5f")])
    if not out:
        return []
    return ["", "Mixed precision (`trainer.precision`): the field's colour net under autocast (its geometry net, "
            "the rays, the occupancy lookups, the guidance's own `precision` and the contrastive logits stay as in "
            "float32), "
            "against the float32 row above. Fidelity: the source field's view rendered both ways (PSNR) and the "
            "parameter gradient of one two-pass backprop of a fixed image gradient (cosine), same samples.", "",
            *common.md_table(["scene", "guide", "trainer.precision", "step speed-up", "field work speed-up",
                              "render vs float32 (dB)", "gradient cosine vs float32"], out)]


def _retained(rows: list[dict[str, Any]]) -> list[str]:
    """``stylize.backprop`` rows against the patch-backprop row of the same scene and guide: time, the graph
    autograd keeps, the gradient's agreement."""
    f = common.fmt
    out = _versus_baseline(rows, "graph_view_mib", "backprop_mode", lambda r: [
        f(r["graph_patch_mib"], ".0f"), f(r["graph_view_mib"], ".0f"), f(r["grad_cos"], ".5f")])
    if not out:
        return []
    return ["", "Memory for time (`stylize.backprop`): `retain` renders the view once with grad (marched, early "
            "termination) and back-propagates through its kept graph; `patch` (the paper's) renders it without grad "
            "and re-renders it patch by patch with grad. Against the patch row above, same run. Graph: the bytes "
            "autograd saves for the backward (the source field's view, parameters included): the largest patch "
            "(what `patch` holds at once) and the whole view (what `retain` holds). Gradient: cosine of the "
            "parameter gradients of both ways for a fixed random image gradient, same samples.", "",
            *common.md_table(["scene", "guide", "stylize.backprop", "step speed-up", "field work speed-up",
                              "graph, one patch (MiB)", "graph, whole view (MiB)", "gradient cosine vs patch"], out)]


def report(raw: dict[str, Any], info: dict[str, Any], cmd: str, quick: bool) -> str:
    f = common.fmt
    body = ["### Part 1: one stylization step at the paper's resolution versus its guidance floor", "",
            "Trained `preset=paper_res` reconstruction (VolSDF + grid, one grid level), its stylization settings "
            "(`stylize.resolution=auto`: the capture's own size; 12 local patches of 1/10 of the view's area; "
            "`stylize.num_samples` 16), medians over the steps (first dropped, source renders excluded). "
            "Floor: forward+backward of the view and its local patches through the guidance's `encode_images`, "
            f"as the step calls it, same run. Goal: step <= {TARGET_RATIO}x the floor.", ""]
    rows = []
    for row in raw.get("steps", []):
        rows.append([row["scene"], f"{row['width']}x{row['height']}", row["guide"], row.get("precision", "32-true"),
                     row.get("backprop_mode", "patch"), f(row["step"]), f(row["render"]), f(row["losses"]),
                     f(row["backprop"]), f(row["floor"]), f"**{f(row['ratio'])}**",
                     "yes" if row["ratio"] <= TARGET_RATIO else "no"])
    body += _measured_by(raw, "steps")
    body += common.md_table(["scene", "view", "guide", "trainer.precision", "stylize.backprop", "step (s)",
                             "pass 1: render (s)", "losses + dL/dI (s)", "pass 2: backprop (s)", "guidance floor (s)",
                             "step / floor", "meets goal"], rows)
    body += _headroom(raw.get("steps", []))
    body += _mixed(raw.get("steps", []))
    body += _retained(raw.get("steps", []))
    prec = [[r["scene"], r["guide"], f(r.get("floor_open_clip")), f"{f(r['floor'])} ({r['floor_dtype']})", f(r["floor_fp32"]),
             f"{f(r.get('perceptual_auto'))} ({r.get('perceptual_dtype', '–')})", f(r.get("perceptual_fp32"))]
            for r in raw.get("steps", []) if "floor_fp32" in r]
    if prec:
        body += ["", "Arithmetic of the frozen networks on this CPU (`guidance.precision`, `guidance.perceptual.precision`; "
                 "`auto` in brackets): the floor's passes and the perceptual network's forward+backward at the view's "
                 "size, same run. Where float32 is faster, set the precision to fp32. The CLIP floor through open_clip "
                 "as loaded (`auto` precision) is the guidance as it ran before 2026-12-05: float32 weights cast by "
                 "autocast on every call, the strided-convolution patch embedding, torch's default attention kernel; "
                 "the guidance now casts its weights once (the same numbers, bit for bit), embeds patches by a matmul "
                 "(the same sums, to rounding) and runs attention with the math kernel on CPU (as close to float32 as "
                 "the default kernel; `tests/test_guidance_clip.py`).", ""]
        body += common.md_table(["scene", "guide", "guidance floor, open_clip as loaded (s)", "guidance floor, auto (s)", "guidance floor, fp32 batched (s)",
                                 "perceptual, auto (s)", "perceptual, fp32 (s)"], prec)
    job = raw.get("job")
    if job:
        body += ["", "### Part 2: the whole paper-resolution job on fangzhou_nature", "",
                 f"`preset=paper_res guidance=imagenet +prompt=\"{job['prompt']}\"` from an empty output root "
                 "(frames at 270x480, the preset's one-level reconstruction, then 4 epochs of the training views at "
                 "270x480), each stage as a user waits for it (training, evaluation, video, meshes).", ""]
        body += _measured_by(raw, "job")
        body += common.md_table(["measurement", "value", "goal", "met"], [
            ["whole job", f"{f(job['job_s'] / 60, '.1f')} min", f"<= {TARGET_JOB_S / 60:.0f} min",
             "yes" if job["job_s"] <= TARGET_JOB_S else "no"],
            ["reconstruction stage", f"{f(job['reconstruct_s'] / 60, '.1f')} min (held-out PSNR {f(job['psnr'])} dB)",
             "", ""],
            ["stylization stage", f"{f(job['stylize_s'] / 60, '.1f')} min ({job['steps']} steps, "
             f"{f(job['step_s'])} s/step)", "", ""],
            ["judge top-5 on held-out views, source -> stylized",
             f"{f(job['top5_source'], '.0%')} -> {f(job['top5'], '.0%')}", "", ""],
        ], align="lrrl")
    return common.section(NAME, "Paper resolution: step cost versus the guidance floor, and the whole job", cmd,
                          info, body, quick)


def main(argv: Optional[list[str]] = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    p.add_argument("--guides", nargs="+", default=list(GUIDES), choices=list(GUIDES))
    p.add_argument("--mixed", nargs="*", default=["bf16-mixed"], choices=MIXED,
                   help=f"trainer.precision values also timed with the {MIXED_GUIDE!r} guide (none: float32 only)")
    p.add_argument("--backprop", nargs="*", default=list(BACKPROPS), choices=BACKPROPS,
                   help=f"stylize.backprop modes also timed with the {MIXED_GUIDE!r} guide (none: the patches only)")
    p.add_argument("--steps", type=int, default=None, help="part 1 steps per configuration (default 6, quick 2)")
    p.add_argument("--reps", type=int, default=None, help="repetitions of the floor timing (default 5, quick 1)")
    p.add_argument("--skip-job", action="store_true", help="part 1 only")
    p.add_argument("--skip-steps", action="store_true", help="part 2 only")
    p.add_argument("--device", default="cpu", help="device of the part-2 job")
    p.add_argument("--out-root", type=Path, default=ROOT / "outputs" / "benchmarks" / "stylization_quality",
                   help="output_root of the part-1 reconstructions (shared with the other benchmarks)")
    p.add_argument("--job-root", type=Path, default=None, help="output_root of the part-2 job (default: empty tmp)")
    p.add_argument("--raw", type=Path, default=None, help="raw JSON (default benchmarks/results/<name>.json)")
    common.add_common_args(p)
    args = p.parse_args(argv)
    info = common.start_logging(log)
    q = args.quick
    shared = common.shared_data()
    raw_path = args.raw or common.raw_path(NAME, q)
    raw: dict[str, Any] = json.loads(raw_path.read_text()) if raw_path.is_file() else {}
    cmd = common.command("paper_resolution.py", argv)
    this_run = {"command": cmd, "utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    if not args.skip_steps:
        raw["steps"] = []
        raw.setdefault("measured_by", {})["steps"] = this_run
        runs = [(g, "32-true", "patch") for g in args.guides]
        runs += [(MIXED_GUIDE, m, "patch") for m in args.mixed if MIXED_GUIDE in args.guides]
        runs += [(MIXED_GUIDE, "32-true", b) for b in args.backprop if MIXED_GUIDE in args.guides]
        for scene in args.scenes:
            for guide, precision, backprop in runs:
                ov = [o.format(shared=shared) for o in SCENES[scene]]
                row = step_cost(ov, guide, args.steps or (2 if q else 6), args.reps or (1 if q else 5),
                                args.out_root, q, precision, backprop)
                raw["steps"].append({"scene": scene, **row})
                common.atomic_write_text(raw_path, json.dumps(raw, indent=1))
    if not args.skip_job:
        job_root = args.job_root or Path(tempfile.mkdtemp(prefix="nerfart_paper_job_"))
        raw["job"] = paper_job(shared, job_root, args.device, q)
        raw.setdefault("measured_by", {})["job"] = this_run
        log.info("paper-resolution job: %s", raw["job"])
        common.atomic_write_text(raw_path, json.dumps(raw, indent=1))
    common.finish(args, NAME, report(raw, info, cmd, q))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
