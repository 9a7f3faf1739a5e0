"""Reconstruction quality / time trade-off on the head: backbone x encoding x samples x resolution.

Each configuration (``backbone`` in nerf/volsdf/neus, ``encoding`` in grid/frequency,
``render.num_samples`` in 32/64/128/192, ``data.resolution`` in 64/128) trains on the
shipped head scene with the default config otherwise (preset balanced), for
``reconstruct.steps`` steps or ``--budget`` seconds of training, whichever comes
first, and is evaluated (masked PSNR, PSNR, SSIM over all held-out views) at
``--checkpoints`` moments of training time (evaluation excluded from the clock;
the same callback as ``benchmarks/reconstruction.py``). The three presets
(``preset=draft|balanced|paper``, at ``data.resolution=128`` so that they are
comparable) run as extra configurations with ``--presets``.

The plot (``benchmarks/figures/tradeoff.png``) shows every (training time, masked
PSNR) checkpoint; the Pareto front (no other point is both faster and better) is
highlighted, and each preset is said to be on the front, near it (within
``--near`` dB of the best PSNR reached by that time), or off it.

The full grid is 48 runs: select a subset, e.g.

    python -m benchmarks tradeoff --backbones volsdf --encodings grid --samples 32 64 --resolutions 64
    python -m benchmarks tradeoff --presets-only
    python -m benchmarks tradeoff --quick
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import sys
from pathlib import Path
from typing import Any, Optional

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common
from benchmarks.reconstruction import load_scene, train_one

log = logging.getLogger("bench.tradeoff")
NAME = "tradeoff"
PRESETS = ("draft", "balanced", "paper")


def pareto(points: list[tuple[float, float]], tol: float = 1.0) -> list[int]:
    """Indices of the points (time s, psnr) not dominated by another (no slower and no worse, and
    better in one). Times within ``tol`` seconds count as equal: every run is evaluated at the same
    budget fractions, and a checkpoint logged at 66.7 s is not faster than one at 66.8 s."""
    def dominates(a: tuple[float, float], b: tuple[float, float]) -> bool:
        (t2, q2), (t, q) = a, b
        return t2 <= t + tol and q2 >= q and (t2 < t - tol or q2 > q)

    front = [i for i, p in enumerate(points) if not any(dominates(o, p) for j, o in enumerate(points) if j != i)]
    return sorted(front, key=lambda i: points[i][0])


def best_by(points: list[tuple[float, float]], t: float, tol: float = 1.0) -> float:
    """Best PSNR among points reached within time ``t`` (+ ``tol`` s, as in ``pareto``)."""
    return max((q for t2, q in points if t2 <= t + tol), default=float("-inf"))


def is_sdf(r: dict[str, Any]) -> bool:
    """Whether a run's backbone has a surface to export (its field class's ``is_sdf``; the presets
    use the default backbone, volsdf)."""
    from nerfart_plugin.config import registry

    return "preset" in r or bool(getattr(registry.get("backbone", r.get("backbone", "")), "is_sdf", False))


def label(cfg: dict[str, Any]) -> str:
    if "preset" in cfg:
        return f"preset={cfg['preset']}"
    return f"{cfg['backbone']}/{cfg['encoding']}/{cfg['samples']}spp/{cfg['resolution']}px"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--backbones", nargs="+", default=["nerf", "volsdf", "neus"], choices=["nerf", "volsdf", "neus"])
    p.add_argument("--encodings", nargs="+", default=["grid", "frequency"], choices=["grid", "frequency"])
    p.add_argument("--samples", type=int, nargs="+", default=[32, 64, 128, 192])
    p.add_argument("--resolutions", type=int, nargs="+", default=[64, 128])
    p.add_argument("--presets", action="store_true", help="also run preset=draft|balanced|paper (at 128 px)")
    p.add_argument("--presets-only", action="store_true", help="only the presets")
    p.add_argument("--preset-names", nargs="+", default=list(PRESETS), choices=PRESETS,
                   help="which presets --presets / --presets-only run (default all three)")
    p.add_argument("--budget", type=float, default=None, help="training seconds per run (default 300; quick 4)")
    p.add_argument("--steps", type=int, default=None, help="max steps per run (default: reconstruct.steps)")
    p.add_argument("--checkpoints", type=int, default=None, help="evaluations per run (default 4; quick 1)")
    p.add_argument("--near", type=float, default=0.5, help="dB below the front that still counts as near it")
    p.add_argument("--override", nargs="*", default=[], help="extra Hydra overrides for every run")
    p.add_argument("--include-results", type=Path, nargs="*", default=[],
                   help="raw JSON of earlier runs of this script (benchmarks/results/tradeoff*.json) to plot and "
                        "rank together with this run; their commands are listed")
    p.add_argument("--report-only", action="store_true",
                   help="train nothing: rank and plot the --include-results only (e.g. two runs made side by side)")
    p.add_argument("--raw", type=Path, default=None, help="where this run's raw JSON goes "
                   "(default benchmarks/results/tradeoff.json)")
    common.add_common_args(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    common.quiet_logs()
    q = args.quick
    subset_flags = ("--backbones", "--encodings", "--samples", "--resolutions", "--presets")
    if q and not any(a.startswith(subset_flags) for a in argv):  # smallest useful smoke grid
        args.backbones, args.encodings, args.samples, args.resolutions = ["volsdf"], ["grid", "frequency"], [8, 16], [16]
        args.presets = True
    budget = args.budget or (4.0 if q else 300.0)
    checkpoints = args.checkpoints or (1 if q else 4)
    extra = list(args.override) + (["reconstruct.batch_rays=128", "render.occupancy.resolution=16"] if q else [])
    info = common.machine_info()
    out, figs = common.output_paths(args)

    configs: list[dict[str, Any]] = []
    if args.report_only:
        if not args.include_results:
            p.error("--report-only needs --include-results with the raw JSON of earlier runs")
    elif not args.presets_only:
        for bb, enc, spp, res in itertools.product(args.backbones, args.encodings, sorted(args.samples),
                                                   sorted(args.resolutions)):
            configs.append({"backbone": bb, "encoding": enc, "samples": spp, "resolution": res,
                            "overrides": [f"data.resolution={res}", f"backbone={bb}", f"encoding={enc}",
                                          f"render.num_samples={spp}"]})
    if (args.presets or args.presets_only) and not args.report_only:
        pres_res = 16 if q else 128
        for name in args.preset_names:
            ov = [f"preset={name}", f"data.resolution={pres_res}"]
            if q:
                ov.append("render.num_samples=8")
            configs.append({"preset": name, "resolution": pres_res, "overrides": ov})

    scenes: dict[tuple, Any] = {}
    results: list[dict[str, Any]] = []
    raw = args.raw or common.raw_path(NAME, q)
    raw.parent.mkdir(parents=True, exist_ok=True)
    this_cmd = common.command(NAME + ".py", argv)
    for cfg in configs:
        ov = ["data=h3ds", *cfg["overrides"], *extra]
        # the loaded scene depends on the data settings only (train_one decides the setup per run)
        key = tuple(o for o in ov if o.startswith(("data.", "preset=")))
        name = label(cfg)
        log.info("== %s (budget %.0f s)", name, budget)
        try:
            if key not in scenes:
                scenes.clear()  # keep one scene in memory
                scenes[key] = load_scene(ov)
            steps = args.steps or int(common.compose(["stage=reconstruct", *ov])["reconstruct"]["steps"])
            cps = [budget * (i + 1) / checkpoints for i in range(checkpoints - 1)]
            r = train_one(scenes[key], ov, budget, cps, 0, True, max_steps=steps)
            results.append({**cfg, "label": name, "command": this_cmd, "budget": budget, "schedule_steps": steps, **r})
        except Exception as exc:  # noqa: BLE001 - one failed configuration must not lose the others
            log.exception("run failed")
            results.append({**cfg, "label": name, "command": this_cmd, "error": f"{type(exc).__name__}: {exc}"})
        raw.write_text(json.dumps(results, indent=1, default=str))  # partial results survive a crash

    by_label: dict[str, dict[str, Any]] = {}  # a later file's run of a configuration replaces an earlier one
    for path in args.include_results:
        try:
            rows = json.loads(Path(path).read_text())
        except (OSError, ValueError) as exc:
            p.error(f"--include-results {path}: cannot read it ({exc}); give the raw JSON a previous run wrote")
        by_label.update({r["label"]: r for r in rows if "label" in r})
    done = {r["label"] for r in results}
    included = [r for lbl, r in by_label.items() if lbl not in done]
    results = results + included
    if args.report_only:  # describe the included runs' settings
        budget = max((float(r["budget"]) for r in included if "budget" in r), default=budget)
        checkpoints = max((len(r.get("records", [])) for r in included), default=checkpoints)
    metric = "psnr_masked"
    # PSNR on 64 px views is not comparable with PSNR on 128 px views (other targets): the front is
    # taken over the runs evaluated at the highest resolution present (the presets' 128 px)
    rank_res = max((int(r.get("resolution", 0)) for r in results), default=0)
    pts, owner = [], []
    for i, r in enumerate(results):
        if int(r.get("resolution", 0)) != rank_res:
            continue
        for rec in r.get("records", []):
            if metric in rec:
                pts.append((rec["time"], rec[metric]))
                owner.append(i)
    front = pareto(pts)
    on_front = {owner[i] for i in front}
    # NeRF-Art stylizes geometry too and exports a mesh: a user who needs a surface chooses among
    # the SDF backbones (the presets use the default volsdf), so that front is reported as well
    sdf_idx = [k for k in range(len(pts)) if is_sdf(results[owner[k]])]
    sdf_pts = [pts[k] for k in sdf_idx]
    sdf_front = [sdf_idx[k] for k in pareto(sdf_pts)]
    on_sdf_front = {owner[k] for k in sdf_front}

    def standing(i: int, sdf_only: bool = False) -> str:
        r = results[i]
        if "error" in r or not r.get("records"):
            return "not measured"
        if int(r.get("resolution", 0)) != rank_res:
            return f"not ranked ({r.get('resolution')} px views)"
        if sdf_only and not is_sdf(r):
            return "–"
        if i in (on_sdf_front if sdf_only else on_front):
            return "ON the front"
        ref = sdf_pts if sdf_only else pts
        gaps = [best_by(ref, rec["time"]) - rec.get(metric, float("-inf")) for rec in r["records"]]
        gap = min(gaps)
        return f"near (-{gap:.2f} dB)" if gap <= args.near else f"off (-{gap:.2f} dB)"

    fig: Optional[Path] = figs / "tradeoff.png"
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        f, ax = plt.subplots(figsize=(11, 5.5))
        # colour = backbone, line style = encoding, marker size = samples per ray; presets as stars
        colours = {"nerf": "tab:blue", "volsdf": "tab:orange", "neus": "tab:green"}
        styles = {"grid": "-", "frequency": ":"}
        seen: set[str] = set()
        for i, r in enumerate(results):
            recs = [x for x in r.get("records", []) if metric in x]
            if not recs or int(r.get("resolution", 0)) != rank_res:
                continue  # other evaluation resolution: not on this PSNR scale
            xs, ys = [x["time"] for x in recs], [x[metric] for x in recs]
            if "preset" in r:
                pc = {"draft": "tab:purple", "balanced": "tab:red", "paper": "tab:brown"}.get(r["preset"], "black")
                ax.plot(xs, ys, marker="*", ms=13, lw=1.5, color=pc, label=r["label"], zorder=4)
                continue
            group = f"{r.get('backbone')}/{r.get('encoding')}"
            ax.plot(xs, ys, color=colours.get(r.get("backbone"), "gray"), ls=styles.get(r.get("encoding"), "-"),
                    marker="o", ms=2 + int(r.get("samples", 32)) / 24, lw=0.8, alpha=0.7,
                    label=f"{group} (dot size: samples/ray)" if group not in seen else None)
            seen.add(group)
        fx = [pts[i][0] for i in front]
        fy = [pts[i][1] for i in front]
        ax.step(fx, fy, where="post", color="black", lw=2, label="Pareto front (all)")
        ax.scatter(fx, fy, color="black", zorder=5)
        sx = [pts[i][0] for i in sdf_front]
        sy = [pts[i][1] for i in sdf_front]
        ax.step(sx, sy, where="post", color="black", lw=1.5, ls="--", label="Pareto front (SDF backbones)")
        ax.set_xlabel("training wall time (s, evaluation excluded)")
        ax.set_ylabel("held-out masked PSNR (dB)")
        ax.set_title("head: quality vs time (backbone x encoding x samples x resolution)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        f.tight_layout()
        fig.parent.mkdir(parents=True, exist_ok=True)
        f.savefig(fig, dpi=120)
        plt.close(f)
    except Exception as exc:  # noqa: BLE001
        log.warning("no plot: %s", exc)
        fig = None

    rows = []
    for i, r in enumerate(results):
        if "error" in r:
            rows.append([r["label"], "error: " + r["error"][:70], "", "", "", "", "", "", "", ""])
            continue
        fin = r["final"]
        sched = r.get("schedule_steps")
        # what finishing the configuration's own schedule (reconstruct.steps) would take at the measured pace
        full = sched * r["sec_per_step"] / 60.0 if sched and r.get("sec_per_step") else None
        full_s = "–" if full is None else (f"{sched} in {full:.0f} min" if full < 120 else f"{sched} in {full / 60:.0f} h")
        rows.append([r["label"], common.fmt(r["train_seconds"], ".0f"), r["steps"], common.fmt(r["sec_per_step"], ".2f"),
                     full_s,
                     common.fmt(fin.get("psnr_masked")), common.fmt(fin.get("psnr")), common.fmt(fin.get("ssim"), ".3f"),
                     standing(i), standing(i, sdf_only=True)])
    body = [
        f"Head scene (shipped h3ds), default config (preset balanced) except the swept settings; each run trains for "
        f"reconstruct.steps steps or {budget:.0f} s of training, whichever comes first"
        + (f" (extra overrides: {' '.join(extra)})" if extra else "") + f"; {checkpoints} evaluation(s) per run on all "
        "held-out views (time excluded). Presets run at data.resolution=128 (paper's native resolution would be 256). "
        f"Pareto front over all checkpoints (time, masked PSNR) of the runs at {rank_res} px (PSNR at another "
        f"resolution is measured against other images and not ranked); 'near' = within {args.near:g} dB of the best PSNR "
        "any configuration reached by the same time.",
        "",
    ]
    others = sorted({r["command"] for r in included if r.get("command") and r["command"] != this_cmd})
    if others:
        if args.report_only:
            body += ["This invocation trained nothing: every row was measured by one of the runs below (their "
                     "machine: this one; a command starting with `taskset` ran pinned to that single core), and "
                     "this report ranks and plots them together (a later run of a configuration replaces an "
                     "earlier one).", ""]
        body += ["Rows from earlier runs of this script on the same machine, ranked together with this one: "
                 + "; ".join(f"`{c}`" for c in others) + ".", ""]
    body += common.md_table(["configuration", "train time (s)", "steps", "s/step", "full schedule at that pace",
                             "masked PSNR (dB)", "PSNR (dB)", "SSIM", "Pareto (all)", "Pareto (SDF: a surface)"],
                            rows, "lrrrrrrrll")
    body += ["", "Pareto front (time s: masked PSNR dB, configuration): "
             + "; ".join(f"{pts[i][0]:.0f}: {pts[i][1]:.2f} ({results[owner[i]]['label']})" for i in front) + "."]
    body += ["", "Pareto front among the SDF backbones (volsdf, neus, and the presets, which use volsdf): "
             + "; ".join(f"{pts[i][0]:.0f}: {pts[i][1]:.2f} ({results[owner[i]]['label']})" for i in sdf_front) + "."]
    pres = [i for i, r in enumerate(results) if "preset" in r]
    if pres:
        body += ["", "Presets (all / among SDF backbones): " + "; ".join(
            f"**{results[i]['preset']}** {standing(i)} / {standing(i, sdf_only=True)}" for i in pres) + "."]
    if fig is not None:
        body += ["", f"![PSNR vs time, Pareto front]({common.rel(fig, out.parent)})"]
    text = common.section(NAME, "Trade-off: reconstruction quality versus time (head)", common.command(NAME + ".py", argv),
                          info, body, q)
    common.finish(args, NAME, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
