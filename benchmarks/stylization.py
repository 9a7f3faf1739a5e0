"""Time per stylization step, its breakdown, and the resolution / local-patch trade-off.

Part 1 (goal: one step < 2x one CLIP ViT-B/32 forward+backward at 224 px):
the project's :class:`~nerfart_plugin.systems.stylization.StylizationSystem` on the
shipped head scene at ``stylize.resolution`` (128), driven by a Lightning
``Trainer``, with the paper's guidance architectures (open_clip ViT-B/32 + VGG16)
built with RANDOM weights (``guidance.allow_random_weights=true``): random weights
cost exactly what the OpenAI/ImageNet weights cost, and none can be downloaded
here. The system records per-step ``timings`` (no-grad render, losses + dL/dI,
patch backprop); CLIP (global view, local patches) and VGG forward+backward at
that resolution are also timed on their own. Reference: one
``open_clip.create_model("ViT-B-32", pretrained=None)`` image forward+backward at
224 px in the same run.

Part 2 (issue 5): time per step and CLIP score after ``--sweep-steps`` steps
versus resolution (64/128/256) and number of local patches (0/4/8/16), with
``--guidance toy`` (default: deterministic toy encoders, the score is the toy
score) or ``--guidance clip`` (needs the CLIP/VGG weights; real scores and times).

The source field (``--source``) is by default the trained head reconstruction of the
same config, as a user gets it: the cached ``final.ckpt`` under
``outputs/reconstructions/`` (made first through the pipeline if missing, ~5 min);
``--source fresh`` uses a freshly initialised field instead (its occupancy grid is fully
occupied, so every ray gets every sample: an upper bound of the per-step cost), and
``--source-checkpoint`` names any ``final.ckpt`` with the same backbone/encoding.

Part 0 (trained source only): fidelity of the no-grad render versus samples per ray
(``stylize.num_samples``), PSNR against a 256-sample render of the same held-out views
at the stylization resolution, and time per view: what the stylization default
(16) costs in accuracy.

    python -m benchmarks stylization
    python -m benchmarks stylization --guidance clip --source-checkpoint outputs/reconstructions/.../final.ckpt
    python -m benchmarks stylization --quick
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable, Optional

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common

log = logging.getLogger("bench.stylization")
NAME = "stylization"
PROMPT = "Vincent van Gogh"
RANDOM_CLIP = ["guidance=clip", "guidance.allow_random_weights=true", "guidance.allow_download=false",
               "guidance.pretrained=null", "guidance.perceptual.weights=null"]
QUICK_OVERRIDES = ["render.num_samples=16", "render.occupancy.resolution=16", "stylize.patch_size=16",
                   "render.chunk=1024", "data.resolution=32", "stylize.num_negatives=8"]


def timed(fn: Callable[[], Any], reps: int) -> float:
    """Median seconds of ``fn()`` over ``reps`` runs after one warm-up."""
    fn()
    out = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return statistics.median(out)


def fwd_bwd(encode: Callable, x_shape: tuple[int, ...]) -> Callable[[], None]:
    import torch

    def run() -> None:
        x = torch.rand(x_shape, requires_grad=True)
        y = encode(x)
        (sum(t.float().mean() for t in y) if isinstance(y, (list, tuple)) else y.float().mean()).backward()

    return run


def clip_reference(reps: int, model_overrides: Optional[dict] = None, batch: int = 1) -> float:
    """open_clip ViT-B/32 (random weights) image forward+backward of ``batch`` images at 224 px in one
    pass, float32, seconds (median); ``batch=1`` is the issue's reference."""
    import open_clip

    net = open_clip.create_model("ViT-B-32", pretrained=None, **(model_overrides or {})).eval()
    for p in net.parameters():
        p.requires_grad_(False)
    size = net.visual.image_size
    size = size if isinstance(size, int) else size[0]
    return timed(fwd_bwd(net.encode_image, (batch, 3, size, size)), reps)


# --------------------------------------------------------------------------- scene and system
class Context:
    """Scene, setup and source weights shared by every run (built through :mod:`nerfart_plugin.run.factories`)."""

    def __init__(self, overrides: list[str], source_checkpoint: Optional[Path], source: str = "fresh") -> None:
        from nerfart_plugin.run.factories import build_scene, load_renderer_state
        from nerfart_plugin.run.stages.reconstruct import ReconstructStage
        from nerfart_plugin.systems.base import build_renderer

        self.base = overrides
        self.occupied: Optional[float] = None
        self.scene = build_scene(common.compose(["stage=reconstruct", *overrides]))
        self.c = self.scene.plain
        if source_checkpoint is None and source == "trained":
            recon = ReconstructStage(self.scene)
            if not recon.folder.finished:
                log.info("no cached reconstruction at %s: reconstructing the head first", recon.folder.path)
            source_checkpoint = recon.run().checkpoint
        self.checkpoint = Path(source_checkpoint) if source_checkpoint is not None else None
        if self.checkpoint is not None:
            self.source_state = load_renderer_state(self.checkpoint, self.scene)
        else:
            import torch

            torch.manual_seed(0)
            self.source_state = build_renderer(self.scene.cfg, self.scene.setup).state_dict()


def view_resolution(ctx: "Context") -> int:
    """The long side (pixels) of the view the stylization step renders: ``stylize.resolution`` as the
    system resolves it (``auto``: the loaded images' own)."""
    from nerfart_plugin.run.factories import stylize_settings

    return int(stylize_settings(ctx.scene).resolution)


def samples_fidelity(ctx: "Context", samples: list[int], resolution: Optional[int] = None,
                     views: int = 3) -> list[dict[str, Any]]:
    """Part 0: PSNR of K-sample renders of the source against a 256-sample render, and seconds per view."""
    import torch

    from nerfart_plugin.objectives.losses import psnr
    from nerfart_plugin.rendering.two_pass import render_fixed_samples
    from nerfart_plugin.systems.base import build_renderer

    r = build_renderer(ctx.scene.cfg, ctx.scene.setup)
    r.load_state_dict(ctx.source_state)
    r.eval()
    scene = ctx.scene.scene
    res = int(resolution or view_resolution(ctx))
    vs = ctx.scene.views((scene.val_ids or scene.train_ids)[:views], res)
    ctx.occupied = r.occupied_fraction if r.occupied_fraction is not None else 1.0

    def render(k: int, perturb: bool) -> list[torch.Tensor]:
        r.num_samples = k
        g = torch.Generator().manual_seed(0)
        return [render_fixed_samples(r, v, 8192, perturb=perturb, generator=g)["rgb"] for v in vs]

    ref = render(256, False)
    out = []
    for k in samples:
        render(k, True)  # warm-up
        t0 = time.perf_counter()
        img = render(k, True)
        secs = (time.perf_counter() - t0) / len(vs)
        val = statistics.fmean(float(psnr(a.clamp(0, 1), b.clamp(0, 1))) for a, b in zip(img, ref))
        out.append({"samples": k, "psnr": val, "seconds": secs, "views": len(vs), "resolution": res})
        log.info("part 0: K=%d: %.2f dB vs K=256, %.3f s/view", k, val, secs)
    return out


def run_steps(ctx: Context, overrides: list[str], steps: int, guidance=None, perceptual=None,
              score: bool = False, clip_overrides: Optional[dict] = None, prompt: str = PROMPT) -> dict[str, Any]:
    """``steps`` stylization steps toward ``prompt`` with the composed config; per-step timings (+ CLIP score)."""
    import lightning as L

    from nerfart_plugin.guidance.style import build_style
    from nerfart_plugin.objectives.evaluation import clip_scores
    from nerfart_plugin.run.factories import build_stylization_system
    from nerfart_plugin.run.fit import train_steps

    c = common.compose(["stage=stylize", f"+prompt={json.dumps(prompt)}", *ctx.base, *overrides])
    L.seed_everything(int(c["seed"]), verbose=False)
    if clip_overrides and c["guidance"]["name"] == "clip":
        c["guidance"]["model_overrides"] = clip_overrides
    scene = ctx.scene.with_config(c)
    style = build_style(scene.cfg, guidance, perceptual)
    system = build_stylization_system(scene, ctx.source_state, style)
    sc = system.cfg

    class Recorder(L.Callback):
        def __init__(self) -> None:
            self.timings: list[dict[str, float]] = []

        def on_train_batch_end(self, trainer, pl_module, *args: Any) -> None:
            self.timings.append(dict(pl_module.timings))

    rec = Recorder()
    train_steps(system, steps, scene.device, scene.cfg.trainer, callbacks=[rec])
    out: dict[str, Any] = {"timings": rec.timings, "resolution": int(sc.resolution),
                           "local_patches": sc.local_patches, "guidance": style.guidance,
                           "perceptual": style.perceptual, "patch_size": sc.patch_size,
                           "num_samples": int(sc.num_samples or scene.cfg.render.num_samples)}
    if score:
        import torch

        system.eval()
        ids = scene.scene.val_ids or scene.scene.train_ids[:4]
        ev = scene.views(ids, sc.resolution)
        with torch.no_grad():
            sty = torch.stack([system.render_batch(v)["rgb"].permute(2, 0, 1) for v in ev]).clamp(0, 1)
            src = torch.stack([system.render_batch(v, source=True)["rgb"].permute(2, 0, 1) for v in ev]).clamp(0, 1)
        out.update(clip_scores(style.guidance, sty, src, style.prompt, style.source_prompt))
    return out


def steady(timings: list[dict[str, float]], skip_first: bool = True) -> dict[str, float]:
    """Median of each timing over the steps (first step dropped when there are more), step without
    the one-off source-view cache."""
    use = timings[1:] if skip_first and len(timings) > 1 else timings
    keys = use[0].keys()
    med = {k: statistics.median(t[k] for t in use) for k in keys}
    med["step_no_cache"] = statistics.median(t["step"] - t["source_cache"] for t in use)
    return med


# --------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--guidance", choices=["toy", "clip"], default="toy", help="guidance of the part-2 sweep")
    p.add_argument("--steps", type=int, default=None, help="part 1 steps (default 6, quick 2); the first is dropped")
    p.add_argument("--reps", type=int, default=None, help="repetitions of the isolated timings (default 5, quick 2)")
    p.add_argument("--resolutions", type=int, nargs="+", default=None, help="part 2 (default 64 128 256)")
    p.add_argument("--patches", type=int, nargs="+", default=None, help="part 2 local patches (default 0 4 8 16)")
    p.add_argument("--sweep-steps", type=int, default=None, help="part 2 steps per configuration (default 10)")
    p.add_argument("--skip-sweep", action="store_true", help="part 1 only")
    p.add_argument("--source", choices=["trained", "fresh"], default=None,
                   help="source field: the cached/trained reconstruction (default) or a fresh one (quick default)")
    p.add_argument("--source-checkpoint", type=Path, default=None, help="a final.ckpt to stylize instead")
    p.add_argument("--samples", type=int, nargs="+", default=None,
                   help="part 0 samples per ray (default 8 12 16 24 32 64; quick 8 16)")
    p.add_argument("--override", nargs="*", default=[], help="extra Hydra overrides for every run")
    p.add_argument("--tiny-clip", action="store_true", help="tests only: a 1-layer CLIP instead of ViT-B/32")
    common.add_common_args(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    common.quiet_logs()
    q = args.quick
    steps = args.steps or (2 if q else 6)
    reps = args.reps or (1 if q else 5)
    resolutions = args.resolutions or ([16] if q else [64, 128, 256])
    patches = args.patches or ([0, 4] if q else [0, 4, 8, 16])
    sweep_steps = args.sweep_steps or (1 if q else 10)
    base = list(args.override) + (QUICK_OVERRIDES if q else [])
    info = common.machine_info()
    out_md, _ = common.output_paths(args)


    from nerfart_plugin.guidance import random_patches

    ctx = Context(base, args.source_checkpoint, args.source or ("fresh" if q else "trained"))
    fidelity = samples_fidelity(ctx, args.samples or ([8, 16] if q else [8, 12, 16, 24, 32, 64]), 32 if q else None) \
        if ctx.checkpoint is not None else []
    res1 = 32 if q else view_resolution(ctx)
    log.info("part 1: %d steps at %d px with random-weight CLIP ViT-B/32 + VGG16", steps, res1)
    tiny = None
    if args.tiny_clip:
        from nerfart_plugin.guidance.clip import TINY_TEST_OVERRIDES as tiny
    r1 = run_steps(ctx, [*RANDOM_CLIP, f"stylize.resolution={res1}"], steps, clip_overrides=tiny)
    t1 = steady(r1["timings"])
    g, perc = r1["guidance"], r1["perceptual"]
    k = int(ctx.c["stylize"]["local_patches"])
    frac = float(ctx.c["stylize"]["local_patch_frac"])
    iso = {
        "clip_global": timed(fwd_bwd(g.encode_image, (1, 3, res1, res1)), reps),
        "clip_local": timed(fwd_bwd(lambda x: g.encode_image(random_patches(x, k, frac, g.input_size)),
                                    (1, 3, res1, res1)), reps) if k > 0 else 0.0,
        "vgg": timed(fwd_bwd(perc.features, (1, 3, res1, res1)), reps),
    }
    ref = clip_reference(reps, tiny)
    # the view and its patches batched in one float32 pass (what the guidance does on CUDA): on a
    # CPU the cost still grows with the number of images, which bounds the step from below
    ref_batched = clip_reference(reps, tiny, batch=1 + k) if k > 0 else ref
    dev = next(g.parameters()).device
    prec = str(g.compute_dtype(dev)).replace("torch.", "") if hasattr(g, "compute_dtype") else "float32"
    iso["clip_one_224"] = timed(fwd_bwd(g.encode_image, (1, 3, 224, 224)), reps)
    ratio = t1["step_no_cache"] / ref
    clip_part = iso["clip_global"] + iso["clip_local"]
    log.info("step %.2f s, CLIP reference %.2f s, ratio %.2f", t1["step_no_cache"], ref, ratio)

    sweep: list[dict[str, Any]] = []
    if not args.skip_sweep:
        gov = RANDOM_CLIP[:1] if args.guidance == "clip" else ["guidance=toy"]
        gcache: dict[str, Any] = {}
        for res in resolutions:
            for n in patches:
                log.info("part 2: %d px, %d local patches, %d steps (%s)", res, n, sweep_steps, args.guidance)
                ov = [*gov, f"stylize.resolution={res}", f"stylize.local_patches={n}"]
                if n == 0:
                    ov.append("experiment.lambda_local=0")
                try:
                    r = run_steps(ctx, ov, sweep_steps, gcache.get("g"), gcache.get("p"), score=True,
                                  clip_overrides=tiny)
                    gcache.setdefault("g", r["guidance"])
                    gcache.setdefault("p", r["perceptual"])
                    s = steady(r["timings"])
                    sweep.append({"resolution": res, "local_patches": n, "step": s["step_no_cache"],
                                  "render_nograd": s["render_nograd"], "losses": s["losses_and_image_grad"],
                                  "patch_backprop": s["patch_backprop"], "clip_score": r["clip_score"],
                                  "clip_score_source": r["clip_score_source"],
                                  "clip_dir": r["clip_directional_similarity"]})
                except Exception as exc:  # noqa: BLE001 - one failed cell must not lose the others
                    log.exception("sweep cell failed")
                    sweep.append({"resolution": res, "local_patches": n, "error": f"{type(exc).__name__}: {exc}"})

    # ------------------------------------------------------------------ report
    f2 = lambda v: common.fmt(v, ".2f")
    body = [
        f"Head scene (shipped h3ds), stylization view {res1}x{res1} px, backbone={ctx.c['backbone']['name']}, "
        f"encoding={ctx.c['encoding']['name']}, {r1['num_samples']} samples/ray, patches of "
        f"{r1['patch_size']}x{r1['patch_size']} rays, {k} local patches, {len(r1['timings'])} steps "
        "(medians, first step dropped; the one-off render of each view's source image is excluded). "
        "Guidance: open_clip ViT-B/32 + VGG16 with RANDOM weights (same architecture, hence the same cost, as the "
        "OpenAI / ImageNet weights, which cannot be downloaded here)"
        + (" — **--tiny-clip: a 1-layer test CLIP, NOT ViT-B/32 (tests only)**" if tiny else "") + ". Source field: "
        + (f"the trained reconstruction `{ctx.checkpoint.relative_to(ROOT) if ctx.checkpoint.is_relative_to(ROOT) else ctx.checkpoint}` "
           f"(occupancy grid {100 * ctx.occupied:.0f}% occupied)." if ctx.checkpoint is not None else
           "freshly initialised: its occupancy grid is fully occupied, so every ray gets every sample; a "
           "trained field skips empty sections, so this is an upper bound of the per-step cost."),
        "",
    ]
    if fidelity:
        body += ["### Part 0: samples per ray while stylizing (render fidelity vs time)", "",
                 f"No-grad render of {fidelity[0]['views']} held-out views at {fidelity[0]['resolution']} px from the "
                 "trained source with K occupancy-guided samples per ray (jittered, as in training), PSNR against the "
                 "same views rendered with 256 samples; seconds per view (mean).", ""]
        body += common.md_table(["samples per ray (K)", "PSNR vs K=256 (dB)", "s / view"],
                                [[f["samples"], f"{f['psnr']:.2f}", f"{f['seconds']:.3f}"] for f in fidelity])
        body += ["", f"The stylization default `stylize.num_samples={ctx.c['stylize']['num_samples']}` is what "
                 "this table supports: beyond ~40 dB the sampling error is far below any style change.", ""]
    body += [
        "### Part 1: one step versus one CLIP forward+backward",
        "",
    ]
    body += common.md_table(["what", "seconds"], [
        ["**one stylization step** (no source cache)", f"**{t1['step_no_cache']:.2f}**"],
        ["– no-grad render of the view (pass 1)", f2(t1["render_nograd"])],
        ["– losses + dL/dI (CLIP, VGG, contrastive)", f2(t1["losses_and_image_grad"])],
        ["– patch backprop (pass 2)", f2(t1["patch_backprop"])],
        [f"isolated: guidance CLIP ({prec}) fwd+bwd of the {res1} px view (resized to 224)", f2(iso["clip_global"])],
        [f"isolated: guidance CLIP ({prec}) fwd+bwd of {k} local patches", f2(iso["clip_local"])],
        [f"isolated: guidance CLIP ({prec}) fwd+bwd of one 224 px image", f2(iso["clip_one_224"])],
        [f"isolated: VGG16 features fwd+bwd at {res1} px", f2(iso["vgg"])],
        ["**reference: open_clip ViT-B-32 (pretrained=None) image fwd+bwd at 224 px, float32**", f"**{ref:.2f}**"],
        [f"same reference model, float32, {1 + k} images (view + {k} patches) in one batched pass", f2(ref_batched)],
    ], "lr")
    body += ["", f"Ratio step / CLIP reference = **{ratio:.2f}** (goal < 2): **{'MET' if ratio < 2 else 'NOT MET'}**"
             + (" (quick run: not judged)" if q else "") + ".",
             "", f"The guidance encodes images in {prec} (`guidance.precision=auto`: bf16 on CPUs with native "
             "bf16, fp16 on CUDA, else float32); the reference is the plain float32 model, as a user would time it.",
             "", f"Floor of the step from CLIP alone: the global view and {k} local patches are {1 + k} CLIP image "
             f"forward+backward passes ({clip_part:.2f} s isolated = {clip_part / ref:.2f}x the reference), so with "
             f"local contrastive patches the goal cannot be met by rendering speed alone (batching the {1 + k} "
             f"images in one float32 pass instead costs {ref_batched:.2f} s = {ref_batched / ref:.2f}x: a CPU's "
             "cost grows with the number of images; a GPU runs such a batch in parallel, not measurable here). Everything else (both "
             f"render passes, VGG, the loss arithmetic) costs {max(t1['step_no_cache'] - clip_part, 0.0):.2f} s = "
             f"**{max(t1['step_no_cache'] - clip_part, 0.0) / ref:.2f}x** the reference."]
    if sweep:
        body += ["", f"### Part 2: resolution and local patches ({args.guidance} guidance, {sweep_steps} steps each)", ""]
        if args.guidance == "toy":
            body += ["Toy guidance: the CLIP score is the TOY encoders' cosine to the prompt (a smoke measure of the "
                     "optimisation, not CLIP), and the time per step does not include CLIP/VGG's real cost (see part 1). "
                     "Run with `--guidance clip` and weights for real figures.", ""]
        rows = []
        for s in sweep:
            if "error" in s:
                rows.append([s["resolution"], s["local_patches"], "error: " + s["error"][:60], "", "", "", "", "", ""])
                continue
            rows.append([s["resolution"], s["local_patches"], f2(s["step"]), f2(s["render_nograd"]), f2(s["losses"]),
                         f2(s["patch_backprop"]), common.fmt(s["clip_score"], ".4f"),
                         common.fmt(s["clip_score_source"], ".4f"), common.fmt(s["clip_dir"], ".3f")])
        body += common.md_table(["resolution", "local patches", "step (s)", "render (s)", "losses (s)",
                                 "backprop (s)", "CLIP score", "source score", "CLIP dir. sim."], rows)
    common.raw_path(NAME, q).write_text(json.dumps({"part0": fidelity, "part1": {"timings": r1["timings"], "isolated": iso,
                                                                "clip_reference": ref, "clip_reference_batched": ref_batched,
                                                                "ratio": ratio},
                                                      "sweep": sweep}, indent=1, default=str))
    text = common.section(NAME, "Stylization: time per step and the resolution / local-patch trade-off",
                          common.command(NAME + ".py", argv), info, body, q)
    common.finish(args, NAME, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
