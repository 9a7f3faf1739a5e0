"""Gaussian-splat export: how closely the splats reproduce the field, at what cost, and what a web viewer shows.

On the shipped head (the main job's settings, ``guidance=imagenet``): its reconstruction and the README's
stylization (``+prompt="brain coral"``). First the bounds: what the surface initialization alone reaches at the
default count (no fitting), and one step of the PyTorch rasterizer (a quarter of a view's tiles, forward and
backward) at each count. Then for each run and each budget (Gaussians x steps; the last is ``export.splat_*``'s
default) the export as ``stage=export export.splats=true`` does it: PSNR and SSIM of the splats against the
field's own renders on the capture's held-out views, the export's time on this machine (by part), the ``.ply``'s
size and that of SuperSplat's compressed ``.ply`` (``@playcanvas/splat-transform``). Goal: >= 28 dB at the
default budget in <= 5 min.

The picture field | our rasterizer | Spark in Chromium (one held-out view, the stylization's default export) goes to
``docs/images/splats.png``, with the agreement of the two splat renderers (silhouette IoU, PSNR).

    python -m benchmarks splats --out-root /tmp/splats                 # trains what is missing, then measures
    python -m benchmarks splats --out-root /tmp/splats --report-only    # the section from the raw file
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks import common

ROOT = Path(__file__).resolve().parents[1]
log = logging.getLogger("bench.splats")
NAME = "splats"
PROMPT = "brain coral"
SETTINGS = ("guidance=imagenet",)
#: (Gaussians, steps); the last is the default of export.splat_count / export.splat_steps
BUDGETS = ((40000, 1500), (20000, 1000), (10000, 500))
#: --quick: a tiny head, two small budgets (a smoke test of the benchmark, not a measurement)
QUICK_SETTINGS = ("data.resolution=32", "reconstruct.steps=60", "stylize.steps=3", "stylize.video_frames=2",
                  "export.resolution=32", "export.texture=false", "render.num_samples=16")
QUICK_BUDGETS = ((500, 10), (1000, 20))
GOAL_DB, GOAL_S = 28.0, 300.0
IMAGES = ROOT / "docs" / "images"

def train(root: Path, prompt: str | None, quick: bool = False) -> Path:
    """The reconstruction (``prompt`` None) or the stylization of ``prompt``, trained or reused."""
    what = ["stage=reconstruct"] if prompt is None else [f"+prompt={json.dumps(prompt)}"]
    return common.trained_run(root, [*SETTINGS, *(QUICK_SETTINGS if quick else ()), *what])


# ---------------------------------------------------------------------- the bounds
def step_seconds(splats: Any, views: Any, repeats: int = 5) -> float:
    """Median seconds of one fitting step of the PyTorch rasterizer (the default share of one view's tiles,
    forward and backward)."""
    from nerfart_plugin.export.splats import SplatFit
    from nerfart_plugin.rendering.splats import Splats, rasterize_tiles, tile_pixels

    params = Splats(*(t.detach().clone().requires_grad_(True) for t in splats.parameters()))
    n_tiles = tile_pixels(views.H, views.W).shape[0]
    per_step = max(1, round(SplatFit().tile_share * n_tiles))
    times = []
    for r in range(repeats):
        tiles = torch.randperm(n_tiles, generator=torch.Generator().manual_seed(r))[:per_step]
        t0 = time.perf_counter()
        rasterize_tiles(params, views.c2w[r % len(views.c2w)], views.K[r % len(views.c2w)], views.H, views.W,
                        tiles)["rgb"].sum().backward()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bounds(run: Any, budgets: tuple[tuple[int, int], ...]) -> dict[str, Any]:
    """The surface initialization's quality at the default count, and one step's cost at each budget's count."""
    from nerfart_plugin.export.splats import SplatFit, field_background, field_views, initial_splats, splat_quality

    cfg = SplatFit()
    ids = run.cameras.train_ids
    held = [i for i in range(len(run.cameras.c2w)) if i not in set(ids)]
    t0 = time.perf_counter()
    views = field_views(run, ids[:4], 0, cfg.resolution)
    per_view = (time.perf_counter() - t0) / 4
    held_views = field_views(run, held, 0, cfg.resolution)
    out: dict[str, Any] = {"field_render_s_per_view": per_view, "resolution": cfg.resolution, "steps": {}}
    for count, _ in budgets:
        t0 = time.perf_counter()
        splats = initial_splats(run.renderer.field, count, cfg.seed)
        init_s = time.perf_counter() - t0
        out["steps"][count] = {"step_s": step_seconds(splats, views), "initialization_s": init_s}
        if count == budgets[-1][0]:
            out["initial"] = splat_quality(splats, held_views, field_background(run))
    log.info("bounds: %s", out)
    return out


# ---------------------------------------------------------------------- the budgets
def export(run: Any, folder: Path, count: int, steps: int, clients: Path | None, resolution: int) -> dict[str, Any]:
    """One export at a budget (as ``stage=export export.splats=true`` does), with its compressed size."""
    from benchmarks.splat_clients import splat_transform

    from nerfart_plugin.export.splats import SplatFit, export_splats

    path = folder / f"splats-{count}-{steps}.ply"
    report = export_splats(run, path, SplatFit(count=count, steps=steps, resolution=resolution))
    if clients is not None:
        compressed = path.with_suffix(".compressed.ply")
        compressed.unlink(missing_ok=True)  # splat-transform does not overwrite
        done = splat_transform(clients, str(path), str(compressed))
        report["compressed_bytes"] = compressed.stat().st_size if done.returncode == 0 else None
    log.info("%s: %d x %d -> %.2f dB, SSIM %.3f in %.0f s", run.folder.name, count, steps, report["psnr"],
             report["ssim"], report["seconds"])
    return report


# ---------------------------------------------------------------------- the picture
def picture(run: Any, ply: Path, clients: Path | None, view: int, resolution: int, to: Path) -> dict[str, Any]:
    """field | our rasterizer | Spark in Chromium, from the held-out camera ``view`` at ``resolution`` px, and
    the agreement of the two splat renderers."""
    from benchmarks.splat_clients import spark_screenshot

    from nerfart_plugin.export.splats import read_ply
    from nerfart_plugin.rendering.splats import rasterize
    from nerfart_plugin.utils.images import label_image, save_image, side_by_side, to_uint8
    from nerfart_plugin.viewer.browser import missing_browser

    cams = run.cameras
    path = run.camera(view, resolution)
    W, H = path.width, path.height
    K = path.K[0].double().numpy()
    c2w = cams.to_world(np.asarray(cams.c2w)[view:view + 1, :3, :4])[0]
    field_img = run.render(view, resolution)["rgb"]
    ours = rasterize(read_ply(ply), torch.tensor(c2w, dtype=torch.float32), torch.tensor(K, dtype=torch.float32),
                     H, W)["rgb"].clamp(0, 1)
    tiles = [label_image(to_uint8(field_img), "field"), label_image(to_uint8(ours), "splats (ours)")]
    out: dict[str, Any] = {"view": view, "resolution": [W, H]}
    if clients is not None and not missing_browser():
        spark = spark_screenshot(clients, ply, c2w, K, W, H)
        a, b = ours.numpy().sum(-1) < 2.9, spark.sum(-1) < 2.9
        out["spark_iou"] = float((a & b).sum() / max(1, (a | b).sum()))
        out["spark_psnr"] = float(-10 * np.log10(((ours.numpy() - spark) ** 2).mean()))
        tiles.append(label_image(to_uint8(spark), "Spark (three.js) in Chromium"))
    row = tiles[0]
    for tile in tiles[1:]:
        row = side_by_side(row, tile, labels=None)
    out["picture"] = str(save_image(row, to))
    return out


# ---------------------------------------------------------------------- the report
def measure(root: Path, prompt: str, quick: bool, figures: Path) -> dict[str, Any]:
    from benchmarks.splat_clients import install_clients, missing_node

    from nerfart_plugin.api import open_run
    from nerfart_plugin.export.splats import SplatFit

    budgets = QUICK_BUDGETS if quick else BUDGETS
    resolution = 32 if quick else SplatFit().resolution
    clients = None if missing_node() else install_clients()
    folders = {"source": train(root, None, quick), "stylized": train(root, prompt, quick)}
    runs = {name: open_run(folder, device="cpu") for name, folder in folders.items()}
    out: dict[str, Any] = {"prompt": prompt, "quick": quick, "folders": {k: str(v) for k, v in folders.items()},
                           "bounds": bounds(runs["source"], budgets), "budgets": {}}
    scratch = root / "splat-bench"
    for name, run in runs.items():
        folder = scratch / name
        folder.mkdir(parents=True, exist_ok=True)
        out["budgets"][name] = [export(run, folder, count, steps, clients, resolution) for count, steps in budgets]
    held = [i for i in range(len(runs["stylized"].cameras.c2w)) if i not in set(runs["stylized"].cameras.train_ids)]
    count, steps = budgets[-1]
    out["picture"] = picture(runs["stylized"], scratch / "stylized" / f"splats-{count}-{steps}.ply", clients, held[0],
                             2 * resolution, (figures if quick else IMAGES) / "splats.png")
    return out


def report(raw: dict[str, Any], info: dict[str, Any], cmd: str) -> str:
    b = raw["bounds"]
    default_count = raw["budgets"]["source"][-1]["gaussians"]
    init = b["initial"]
    body = [f"The shipped head, its reconstruction and `+prompt=\"{raw['prompt']}\"` (the main job's settings, "
            "`guidance=imagenet`), fitted at the field's renders of the capture's training views and 24 orbit "
            f"views at {raw['budgets']['source'][-1]['resolution']} px; quality on the held-out views at the same "
            "size." + (" **Quick run: a tiny head and budgets, not a measurement.**" if raw.get("quick") else ""), "",
            f"Bounds: the surface initialization alone ({default_count} Gaussians, no fitting) reaches "
            f"{init['psnr']:.2f} dB / SSIM {init['ssim']:.3f}; the field renders a view in "
            f"{b['field_render_s_per_view']:.2f} s; one fitting step of the PyTorch rasterizer (a quarter of a "
            "view's tiles, forward and backward) costs "
            + ", ".join(f"{v['step_s']:.3f} s at {int(k)}" for k, v in b["steps"].items()) + " Gaussians.", ""]
    rows = []
    for name, reports in raw["budgets"].items():
        for r in reports:
            parts = r["seconds_by_part"]
            rows.append([name, r["gaussians"], r["steps"], f"{r['psnr']:.2f}", f"{r['ssim']:.3f}",
                         f"{r['psnr_initial']:.2f}", f"{r['seconds']:.0f}", f"{parts.get('fit', 0):.0f}",
                         f"{r['bytes'] / 2**20:.1f}",
                         common.fmt((r.get("compressed_bytes") or None) and r["compressed_bytes"] / 2**20, ".2f")])
    body += common.md_table(["run", "Gaussians", "steps", "PSNR vs field (dB)", "SSIM", "PSNR at initialization",
                             "export (s)", "of it fitting (s)", ".ply (MiB)", "compressed .ply (MiB)"], rows)
    default = {name: reports[-1] for name, reports in raw["budgets"].items()}
    met = all(r["psnr"] >= GOAL_DB and r["seconds"] <= GOAL_S for r in default.values())
    body += ["", f"Goal at the default budget (>= {GOAL_DB:.0f} dB in <= {GOAL_S / 60:.0f} min): "
             + ("**met**" if met else "**not met**") + " ("
             + "; ".join(f"{n}: {r['psnr']:.2f} dB in {r['seconds']:.0f} s" for n, r in default.items()) + ")."]
    body += more_is_worse(raw["budgets"])
    p = raw["picture"]
    if "spark_iou" in p:
        body += ["", f"Spark in headless Chromium against our rasterizer on the same file and camera (held-out view "
                 f"{p['view']}, {p['resolution'][0]} x {p['resolution'][1]} px): silhouette IoU {p['spark_iou']:.3f}, "
                 f"PSNR {p['spark_psnr']:.1f} dB."]
    body += ["", f"![field | splats | Spark]({common.rel(Path(p['picture']), ROOT)})"]
    return common.section(NAME, "Gaussian-splat export", cmd, info, body, False)


def more_is_worse(budgets: dict[str, list[dict[str, Any]]]) -> list[str]:
    """A line when a larger count fitted worse than a smaller one (and where the initialization already did)."""
    lines = []
    for name, reports in budgets.items():
        by_count = sorted(reports, key=lambda r: r["gaussians"])
        if by_count[-1]["psnr"] < by_count[0]["psnr"]:
            lo, hi = by_count[0], by_count[-1]
            lines.append(f"{name}: {hi['gaussians']} Gaussians fit worse than {lo['gaussians']} ({hi['psnr']:.2f} "
                         f"against {lo['psnr']:.2f} dB), and their initialization already was ({hi['psnr_initial']:.2f} "
                         f"against {lo['psnr_initial']:.2f} dB)")
    if not lines:
        return []
    return ["", "More Gaussians are not better at this fitting resolution: " + "; ".join(lines) + ". At 128 px a "
            "larger count puts several Gaussians on each pixel; the default is the count that fitted best here. Why "
            "the initialization falls with the count (and whether a larger export.splat_resolution recovers it) is "
            "not isolated yet."]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out-root", type=Path, default=ROOT / "outputs" / "benchmarks" / "splats")
    p.add_argument("--prompt", default=PROMPT)
    common.add_raw_args(p)
    common.add_common_args(p)
    args = p.parse_args(argv)
    info = common.start_logging(log)
    _, figures = common.output_paths(args)
    raw = common.raw_results(args, NAME, lambda: measure(args.out_root, args.prompt, args.quick, figures))
    common.finish(args, NAME, report(raw, info, common.command("splats.py", argv or sys.argv[1:])))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
