"""Held-out PSNR versus wall time for each backbone, on the default head scene and on fern.

For each backbone (nerf, volsdf, neus) x scene:

* ``head``: the shipped head scene (``data=h3ds``, ``data.path`` unset) at its native 256x256
  (the paper's resolution), budget 600 s; metric: PSNR inside the mattes (``psnr_masked``),
  full-image PSNR and SSIM reported too; target (issue 12): >= 27 dB with an SDF backbone;
* ``fern``: LLFF fern (``data=llff data.path=../shared/data/llff_fern data.factor=8``,
  504x378, NDC), budget 900 s; metric: PSNR; target: >= 24 dB with the fastest backbone.

Training is the project's :class:`~nerfart_plugin.systems.reconstruction.ReconstructionSystem`
driven by a Lightning ``Trainer`` on the Hydra-composed config (default preset
``balanced``), with a callback that stops at the time budget and, at
``--checkpoints`` evenly spaced moments of *training* time, renders held-out
views and records (training seconds, step, PSNR, masked PSNR, SSIM). Evaluation
time is excluded from the training clock. The LR decay and NeuS variance
anneal, which the system schedules over ``reconstruct.steps``, are scheduled
over the number of steps expected to fit in the budget (re-estimated from the
measured step rate at each checkpoint); ``--fixed-schedule`` keeps ``reconstruct.steps``.

Writes its section of BENCHMARKS.md (``<!-- reconstruction:start/end -->``) and
``benchmarks/figures/reconstruction.png``.

    python -m benchmarks reconstruction                       # full: ~80-120 min on 2 CPU cores
    python -m benchmarks reconstruction --quick               # smoke run (< 2 min), scratch output
    python -m benchmarks reconstruction --scenes head --backbones neus volsdf
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from pathlib import Path
from typing import Any, Optional

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common

log = logging.getLogger("bench.reconstruction")
NAME = "reconstruction"
BACKBONES = ("nerf", "volsdf", "neus")


def scene_specs() -> dict[str, dict[str, Any]]:
    fern = common.shared_data() / "llff_fern"
    return {
        "head": {"overrides": ["data=h3ds"], "budget": 600.0, "metric": "psnr_masked",
                 "target": 27.0, "label": "head (shipped h3ds scene, native 256x256)", "eval_stride": 1,
                 "quick": ["data.resolution=32"]},
        "fern": {"overrides": ["data=llff", f"data.path={fern}", "data.factor=8"], "budget": 900.0,
                 "metric": "psnr", "target": 24.0, "label": "fern (LLFF images_8, 504x378, NDC)", "eval_stride": 4,
                 "quick": ["data.resolution=48"]},
    }


QUICK_OVERRIDES = ["render.num_samples=16", "reconstruct.batch_rays=256", "render.occupancy.resolution=16",
                   "render.occupancy.warmup_steps=8", "render.occupancy.update_every=4"]


# --------------------------------------------------------------------------- the budget callback
def _budget_callback(budget: float, checkpoints: list[float], evaluate, stretch_schedule: bool):
    import lightning as L

    class BudgetEval(L.Callback):
        """Stops at ``budget`` seconds of training; evaluates at the ``checkpoints`` (training seconds)."""

        def __init__(self) -> None:
            self.records: list[dict[str, Any]] = []
            self.eval_seconds = 0.0
            self.pending = sorted(checkpoints)
            self.t0: Optional[float] = None

        def train_seconds(self) -> float:
            return time.perf_counter() - self.t0 - self.eval_seconds

        def on_train_start(self, trainer, pl_module) -> None:
            self.t0 = time.perf_counter()

        def _reschedule(self, trainer, pl_module, t: float) -> None:
            step = max(1, trainer.global_step)
            total = max(step + 1, int(step + (budget - t) * step / max(t, 1e-9)))
            total = min(total, int(trainer.max_steps))
            pl_module.total_steps = total  # the system's LR decay (lr_factor) and NeuS anneal follow it

        def _record(self, trainer, pl_module, t: float, final: bool) -> None:
            e0 = time.perf_counter()
            metrics = evaluate(pl_module, final=final)
            pl_module.train()
            self.eval_seconds += time.perf_counter() - e0
            self.records.append({"time": t, "step": trainer.global_step, "eval_seconds": time.perf_counter() - e0,
                                 "final": final, **metrics})
            log.info("  t=%6.1f s step %5d: %s", t, trainer.global_step,
                     ", ".join(f"{k} {v:.3f}" for k, v in metrics.items() if isinstance(v, float)))

        def on_train_batch_end(self, trainer, pl_module, *args: Any) -> None:
            t = self.train_seconds()
            step = trainer.global_step
            if stretch_schedule and step == 20:
                self._reschedule(trainer, pl_module, t)
            done = t >= budget or step >= trainer.max_steps
            if (self.pending and t >= self.pending[0]) or done:
                while self.pending and self.pending[0] <= t:
                    self.pending.pop(0)
                self._record(trainer, pl_module, t, done)
                if stretch_schedule and not done:
                    self._reschedule(trainer, pl_module, t)
            if done:
                trainer.should_stop = True

    return BudgetEval()


# --------------------------------------------------------------------------- one run
def load_scene(overrides: list[str]):
    """The loaded scene (:func:`nerfart_plugin.run.factories.build_scene`) with its training rays precomputed
    (shared by all backbones)."""
    from nerfart_plugin.run.factories import build_scene

    scene = build_scene(common.compose(["stage=reconstruct", *overrides]))
    scene.dm.setup("fit")
    return scene


def strided_view(batch: dict[str, Any], stride: int) -> dict[str, Any]:
    """Every ``stride``-th row and column of a full-view ray batch (ints ``H``, ``W`` updated)."""
    import torch

    if stride <= 1:
        return batch
    H, W = int(batch["H"]), int(batch["W"])
    out: dict[str, Any] = {}
    for k, v in batch.items():
        if torch.is_tensor(v) and v.dim() > 0 and v.shape[0] == H * W:
            out[k] = v.reshape(H, W, *v.shape[1:])[::stride, ::stride].reshape(-1, *v.shape[1:])
        else:
            out[k] = v
    out["H"], out["W"] = len(range(0, H, stride)), len(range(0, W, stride))
    return out


def train_one(scene, overrides: list[str], budget: float, checkpoints: list[float], eval_views: int,
              stretch_schedule: bool, max_steps: int = 10**9, eval_stride: int = 1) -> dict[str, Any]:
    """Train one backbone on the loaded ``scene`` for ``budget`` s of training (or ``max_steps``);
    returns the checkpoint records and the final metrics (all held-out views)."""
    import lightning as L
    import torch

    from nerfart_plugin.objectives.evaluation import mean_metrics, view_metrics
    from nerfart_plugin.run.factories import build_reconstruction_system
    from nerfart_plugin.run.fit import train_steps

    ctx = scene.with_config(common.compose(["stage=reconstruct", *overrides]))  # this run's render settings
    L.seed_everything(ctx.cfg.seed, verbose=False)
    system = build_reconstruction_system(ctx)
    views = [ctx.dm.view_batch(i) for i in (ctx.scene.val_ids or ctx.scene.train_ids[:1])]
    # intermediate checkpoints: the first eval_views views, every eval_stride-th pixel (final: all, full)
    quick_views = [strided_view(v, eval_stride) for v in (views if eval_views <= 0 else views[:eval_views])]
    chunk = ctx.cfg.render.chunk

    @torch.no_grad()
    def evaluate(module, final: bool) -> dict[str, float]:
        module.eval()
        use = views if final else quick_views
        per = []
        for b in use:
            img = module.render_view(b, chunk=chunk, with_normals=False)  # PSNR/SSIM need colour only
            per.append(view_metrics(img["rgb"], b["rgb"].reshape(img["rgb"].shape).to(img["rgb"].device),
                                    b.get("mask")))
        return {**mean_metrics(per), "views": len(use)}

    cb = _budget_callback(budget, checkpoints, evaluate, stretch_schedule)
    w0 = time.perf_counter()
    fit = train_steps(system, int(max_steps), ctx.device, ctx.cfg.trainer, callbacks=[cb])
    wall = time.perf_counter() - w0
    final = cb.records[-1] if cb.records else {}
    return {"records": cb.records, "final": final, "steps": fit.steps, "setup": ctx.setup.to_dict(),
            "train_seconds": final.get("time", float("nan")), "eval_seconds": cb.eval_seconds, "wall_seconds": wall,
            "sec_per_step": final.get("time", float("nan")) / max(1, fit.steps), "views": len(views)}


# --------------------------------------------------------------------------- report
def first_reaching(records: list[dict], metric: str, target: float) -> Optional[float]:
    """Training seconds at which an intermediate (one-view) checkpoint first reached ``target``; the final
    all-view evaluation is not one of them."""
    for r in records:
        if not r.get("final") and r.get(metric, -math.inf) >= target:
            return float(r["time"])
    return None


def verdicts(results: dict, specs: dict, scale: float, quick: bool) -> list[str]:
    """Each target judged on the FINAL figure (all held-out views at full resolution); an intermediate
    checkpoint (one view, maybe every N-th pixel) reaching it is reported, never counted."""
    lines = ["**Targets**" + (" (not judged: quick run / scaled budget)" if quick or scale != 1.0 else "")
             + " (judged on the final evaluation of all held-out views):", ""]
    head, fern = results.get("head"), results.get("fern")
    if head is not None:
        s = specs["head"]
        for bb in ("neus", "volsdf"):
            r = head.get(bb)
            if r is None or "error" in r:
                lines.append(f"- head, {bb}: not measured" + (f" ({r['error']})" if r else "") + ".")
                continue
            v = r["final"].get(s["metric"], float("nan"))
            t = first_reaching(r["records"], s["metric"], s["target"])
            lines.append(f"- head >= {s['target']:.0f} dB masked PSNR within {s['budget'] * scale:.0f} s, {bb}: "
                         f"**{'MET' if v >= s['target'] else 'NOT MET'}** (masked PSNR {v:.2f} dB at "
                         f"{r['train_seconds']:.0f} s" + _checkpoint_note(t) + ").")
    if fern is not None:
        s = specs["fern"]
        ok_runs = {bb: r for bb, r in fern.items() if "error" not in r}
        if not ok_runs:
            lines.append("- fern: not measured.")
        else:
            best = max(ok_runs, key=lambda b: ok_runs[b]["final"].get("psnr", -1))
            fastest = min(ok_runs, key=lambda b: ok_runs[b]["sec_per_step"])
            v = ok_runs[fastest]["final"].get("psnr", float("nan"))
            t = first_reaching(ok_runs[fastest]["records"], "psnr", s["target"])
            lines.append(f"- fern >= {s['target']:.0f} dB PSNR within {s['budget'] * scale:.0f} s with the fastest "
                         f"backbone ({fastest}, {ok_runs[fastest]['sec_per_step']:.2f} s/step): "
                         f"**{'MET' if v >= s['target'] else 'NOT MET'}** ({v:.2f} dB" + _checkpoint_note(t) + ").")
            lines.append(f"  Highest PSNR on fern: {best} ({ok_runs[best]['final'].get('psnr', float('nan')):.2f} dB).")
    return lines


def _checkpoint_note(t: Optional[float]) -> str:
    return f"; an intermediate one-view checkpoint first reached the target at {t:.0f} s" if t is not None else ""


def plot(results: dict, specs: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = [s for s in specs if s in results]
    fig, axes = plt.subplots(1, len(scenes), figsize=(5.5 * len(scenes), 4), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        s = specs[scene]
        for bb, r in results[scene].items():
            if "error" in r or not r["records"]:
                continue
            xs = [0.0] + [x["time"] for x in r["records"]]
            ys = [float("nan")] + [x.get(s["metric"], float("nan")) for x in r["records"]]
            ax.plot(xs[1:], ys[1:], marker="o", label=bb)
        ax.axhline(s["target"], color="gray", ls="--", lw=1, label=f"target {s['target']:.0f} dB")
        ax.set_xlabel("training wall time (s, evaluation excluded)")
        ax.set_ylabel("held-out " + ("masked PSNR" if s["metric"] == "psnr_masked" else "PSNR") + " (dB)")
        ax.set_title(s["label"])
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _defaults_text() -> str:
    """The sampling settings of the default config, as composed now (not hard-coded)."""
    c = common.compose([])
    enc = c["encoding"]
    res = enc.get("resolution")
    res_text = (f"side chosen per scene, about {enc.get('cell_pixels')} image px per cell" if res == "auto"
                else f"side {res}")
    if enc.get("levels") == "auto":
        res_text += ", levels chosen per backbone"
    elif enc.get("levels") not in (None, 1):
        res_text += f", {enc.get('levels')} levels"
    return (f"{enc['name']} encoding ({res_text}), {c['render']['num_samples']} samples/ray, occupancy grid "
            f"{c['render']['occupancy']['resolution']}^3 where the scene setup keeps one, sampling "
            f"{c['render']['occupancy']['sampling']}, {c['reconstruct']['batch_rays']} rays/step")


def _setup_text(setup: dict) -> list[str]:
    """The decided sizes and sampling of one run's scene setup, as short phrases."""
    grid, levels = setup.get("grid_resolution"), setup.get("grid_levels")
    occ = setup.get("occupancy_resolution", 0)
    share, matte = setup.get("mask_ray_share"), setup.get("matte_fraction")
    return [f"grid encoding side {grid if grid else 'as configured'}"
            + (f", {levels} levels" if levels and levels > 1 else ""),
            f"occupancy grid {occ}^3, {setup.get('occupancy_sampling')} sampling" if occ else "no occupancy grid, "
            "uniform samples", f"{setup.get('num_samples')} samples/ray",
            *([f"mattes on {matte:.0%} of the training pixels, {share:.0%} of each batch drawn inside them "
               "(reconstruct.mask_ray_share=auto)"] if share is not None and matte is not None else [])]


def report(results: dict, specs: dict, args: argparse.Namespace, argv: list[str], info: dict, fig: Optional[Path],
           out: Path, extra: list[str], note: str = "") -> str:
    body = ([f"> Note on this run: {note}", ""] if note else []) + [
        "Held-out PSNR versus training wall time, one backbone at a time, default config (preset balanced: "
        + _defaults_text() + (", plus " + " ".join(extra) if extra else "")
        + "; the scene setup decides the rest per scene, as listed below the table where the run recorded it). "
        "Time is training only: the held-out evaluations at the checkpoints are excluded. "
        f"Intermediate checkpoints (curves) render {'all' if args.eval_views <= 0 else args.eval_views} held-out "
        "view(s), on every N-th pixel row and column ("
        + ", ".join(f"{k}: N={v.get('eval_stride_used', v['eval_stride'])}" for k, v in specs.items() if k in results)
        + "); the table's final figures render all held-out views at full resolution. The LR decay / NeuS anneal are scheduled over the steps "
        "expected to fit in the budget" + (" (disabled: --fixed-schedule)" if args.fixed_schedule else "") + ".",
        "",
    ]
    rows = []
    for scene, per in results.items():
        for bb, r in per.items():
            if "error" in r:
                rows.append([scene, bb, "error: " + r["error"][:80], "", "", "", "", "", "", ""])
                continue
            f = r["final"]
            t_hit = first_reaching(r["records"], specs[scene]["metric"], specs[scene]["target"])
            rows.append([scene, bb, common.fmt(r["train_seconds"], ".0f"), r["steps"],
                         common.fmt(r["sec_per_step"], ".2f"), common.fmt(f.get("psnr")),
                         common.fmt(f.get("psnr_masked")), common.fmt(f.get("ssim"), ".3f"),
                         common.fmt(t_hit, ".0f", none="not reached"), common.fmt(r["eval_seconds"], ".0f")])
    body += common.md_table(["scene", "backbone", "train time (s)", "steps", "s/step", "PSNR (dB)",
                             "masked PSNR (dB)", "SSIM", "a one-view checkpoint >= target at (s)", "eval time (s)"], rows,
                            "ll" + "r" * 8)
    setups = [f"- {scene} / {bb}: " + "; ".join(_setup_text(r["setup"]))
              for scene, per in results.items() for bb, r in per.items() if r.get("setup")]
    if setups:
        body += ["", "Scene setup of each run (systems/scene_setup.py):", "", *setups]
    body += ["", "Target metric per scene: " + ", ".join(
        f"{k} = {'masked PSNR' if v['metric'] == 'psnr_masked' else 'PSNR'} >= {v['target']:.0f} dB"
        for k, v in specs.items() if k in results) + ".", ""]
    body += verdicts(results, specs, args.budget_scale, args.quick)
    body += ["", "Curves (training seconds: metric; the last point, marked *, is the final all-view evaluation, the "
             "others one view, so the step into it is partly a change of views):", ""]
    for scene, per in results.items():
        m = specs[scene]["metric"]
        for bb, r in per.items():
            if "error" not in r:
                pts = ", ".join(f"{x['time']:.0f}{'*' if x.get('final') else ''}: {x.get(m, float('nan')):.2f}"
                                for x in r["records"])
                body.append(f"- {scene} / {bb} ({m}): {pts}")
    if fig is not None:
        body += ["", f"![PSNR vs time]({common.rel(fig, out.parent)})"]
    return common.section(args.section, "Reconstruction: held-out PSNR versus wall time (" + ", ".join([*args.scenes, *extra]) + ")", common.command(NAME + ".py", argv),
                          info, body, args.quick)


# --------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--backbones", nargs="+", default=list(BACKBONES), choices=BACKBONES)
    p.add_argument("--scenes", nargs="+", default=["head", "fern"], choices=["head", "fern"])
    p.add_argument("--budget-scale", type=float, default=None,
                   help="multiply the time budgets (head 600 s, fern 900 s); default 1 (quick: 0.015)")
    p.add_argument("--checkpoints", type=int, default=None, help="evaluations per run (default 10; quick 2)")
    p.add_argument("--eval-views", type=int, default=None,
                   help="held-out views rendered at intermediate checkpoints (0 = all; default 1)")
    p.add_argument("--eval-stride", type=int, default=None,
                   help="intermediate checkpoints use every N-th pixel row/column (default: head 1, fern 4)")
    p.add_argument("--fixed-schedule", action="store_true", help="schedule LR/anneal over reconstruct.steps")
    p.add_argument("--override", nargs="*", default=[], help="extra Hydra overrides for every run")
    p.add_argument("--section", default=NAME, help="name of the BENCHMARKS.md section to write (default: reconstruction)")
    p.add_argument("--raw", type=Path, default=None, help="raw results JSON (default outputs/benchmarks/<section>.json; "
                   "real runs behind BENCHMARKS.md are kept in benchmarks/results/)")
    p.add_argument("--report-only", action="store_true", help="train nothing: rebuild the section and figure from --raw "
                   "(its command, machine and settings are the run's)")
    common.add_common_args(p)
    args = p.parse_args(argv)
    if args.report_only:
        return report_only(args)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    common.quiet_logs()
    if args.budget_scale is None:
        args.budget_scale = 0.015 if args.quick else 1.0
    if args.checkpoints is None:
        args.checkpoints = 2 if args.quick else 10
    if args.eval_views is None:
        args.eval_views = 1
    info = common.machine_info()
    out, figs = common.output_paths(args)
    specs = scene_specs()
    extra = list(args.override) + (QUICK_OVERRIDES if args.quick else [])

    results: dict[str, dict[str, Any]] = {}
    for scene in args.scenes:
        s = specs[scene]
        scene_ov = s["overrides"] + (s["quick"] if args.quick else []) + extra
        s["overrides_used"] = scene_ov
        budget = s["budget"] * args.budget_scale
        stride = args.eval_stride or (1 if args.quick else s["eval_stride"])
        s["eval_stride_used"] = stride
        cps = [budget * (i + 1) / args.checkpoints for i in range(args.checkpoints - 1)]
        log.info("== %s: loading (%s)", scene, " ".join(scene_ov))
        try:
            pipe = load_scene([*scene_ov, f"backbone={args.backbones[0]}"])  # each run decides its own setup
        except Exception as exc:  # noqa: BLE001 - report and go on with the other scene
            log.error("cannot load %s: %s", scene, exc)
            results[scene] = {bb: {"error": f"{type(exc).__name__}: {exc}"} for bb in args.backbones}
            continue
        results[scene] = {}
        for bb in args.backbones:
            log.info("== %s / %s: budget %.0f s", scene, bb, budget)
            try:
                results[scene][bb] = train_one(pipe, [*scene_ov, f"backbone={bb}"], budget, cps, args.eval_views,
                                               not args.fixed_schedule, eval_stride=stride)
            except Exception as exc:  # noqa: BLE001
                log.exception("run failed")
                results[scene][bb] = {"error": f"{type(exc).__name__}: {exc}"}
        del pipe
    fig = figs / f"{args.section}.png"
    try:
        plot(results, specs, fig)
    except Exception as exc:  # noqa: BLE001
        log.warning("no plot: %s", exc)
        fig = None
    raw = args.raw or (out.parent / "outputs" / "benchmarks" / f"{args.section}{'.quick' if args.quick else ''}.json"
                       if out.parent == ROOT else out.parent / f"{args.section}.json")
    raw.parent.mkdir(parents=True, exist_ok=True)
    saved_info = {**info, "total_s": time.perf_counter() - info["t0"]}
    raw.write_text(json.dumps({"args": vars(args) | {"out": str(out), "figures": str(figs)}, "argv": argv,
                               "info": saved_info, "results": results}, default=str, indent=1))
    common.finish(args, args.section, report(results, specs, args, argv, saved_info, fig, out, extra))
    return 0


def report_only(args: argparse.Namespace) -> int:
    """The section of a saved run (``--raw``): its results, settings, command and machine, re-plotted."""
    if args.raw is None or not args.raw.is_file():
        raise SystemExit(f"--report-only needs --raw FILE of a finished run (got {args.raw})")
    saved = json.loads(args.raw.read_text())
    run_args = argparse.Namespace(**{**saved["args"], "no_write": args.no_write, "out": args.out,
                                     "figures": args.figures, "quick": saved["args"].get("quick", False)})
    out, figs = common.output_paths(run_args)
    specs = scene_specs()
    fig = figs / f"{run_args.section}.png"
    plot(saved["results"], specs, fig)
    text = report(saved["results"], specs, run_args, saved["argv"], saved["info"], fig, out,
                  list(saved["args"].get("override") or []), saved.get("note", ""))
    common.finish(run_args, run_args.section, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
