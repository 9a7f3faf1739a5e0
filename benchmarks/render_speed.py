"""No-grad rendering speed versus fidelity at the paper's resolution.

What a user waits for in every evaluation, video and stylization step is a full view
rendered without grad. This benchmark renders held-out views of a trained
reconstruction at the capture's own resolution (270x480 for the selfie
``fangzhou_nature``, 256x256 for the shipped head) and compares:

* ``dense``: every section of every ray evaluated in one pass
  (``render.stop_transmittance=0``; the renderer before early termination);
* ``march``: :meth:`~nerfart_plugin.rendering.renderer.VolumeRenderer.march`, early ray
  termination at ``render.stop_transmittance`` (default 1e-4), rays that miss the
  occupancy grid never evaluated;

each at several samples per ray K, against a reference render of the same views with
256 samples per ray (dense, unperturbed). Figures: seconds per view (median of
``--reps`` after a warm-up), PSNR against the reference, field evaluations per ray.
Goal (issue 12): a 270x480 selfie view in <= 1.5 s at >= 40 dB.

The reconstructions are the pipeline's own (cached under ``--out-root``, made first if
missing, as ``benchmarks/stylization_quality.py`` makes them).

    python -m benchmarks render_speed
    python -m benchmarks render_speed --scenes fangzhou_nature --samples 16 24 32
    python -m benchmarks render_speed --quick
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common

log = logging.getLogger("bench.render_speed")
NAME = "render_speed"
SCENES: dict[str, list[str]] = {
    "fangzhou_nature": ["data=h3ds", "data.path={shared}/fangzhou_nature"],
    "head": ["data=h3ds"],
}
REFERENCE_SAMPLES = 256
TARGET_SECONDS, TARGET_PSNR = 1.5, 40.0
QUICK = ["data.resolution=48", "reconstruct.steps=200", "reconstruct.val_every=1000", "render.occupancy.resolution=16",
         "export.enabled=false"]


def trained_scene(overrides: list[str]) -> tuple[Any, dict]:
    """The scene context and the trained renderer tensors of its (cached) reconstruction."""
    from nerfart_plugin.run.factories import build_scene, load_renderer_state
    from nerfart_plugin.run.stages.reconstruct import ReconstructStage

    scene = build_scene(common.compose(["stage=reconstruct", *overrides]))
    recon = ReconstructStage(scene)
    if not recon.folder.finished:
        log.info("no cached reconstruction at %s: reconstructing first", recon.folder.path)
    ckpt = recon.run().checkpoint
    return scene, load_renderer_state(ckpt, scene)


def measure(scene: Any, state: dict, samples: list[int], views: int, reps: int) -> dict[str, Any]:
    """Seconds per view, PSNR vs the 256-sample reference and evaluations per ray, per (mode, K)."""
    import torch

    from nerfart_plugin.objectives.losses import psnr
    from nerfart_plugin.systems.base import build_renderer

    r = build_renderer(scene.cfg, scene.setup)
    r.load_state_dict(state)
    r.eval()
    sc = scene.scene
    ids = (sc.val_ids or sc.train_ids)[:views]
    vs = scene.views(ids, max(sc.height, sc.width))
    chunk = int(scene.cfg.render.chunk)
    stop = r.stop_transmittance

    def render(k: int, mode: str) -> tuple[list[torch.Tensor], float]:
        r.num_samples = k
        r.stop_transmittance = stop if mode == "march" else 0.0
        imgs, evaluated, rays = [], 0, 0
        for v in vs:
            n = v["rays_o"].shape[0]
            out = [r.march({kk: (x[s:s + chunk] if torch.is_tensor(x) and x.dim() and x.shape[0] == n else x)
                            for kk, x in v.items()}) for s in range(0, n, chunk)]
            imgs.append(torch.cat([o["rgb"] for o in out]).clamp(0, 1))
            evaluated += sum(int(o["samples_evaluated"]) for o in out)
            rays += n
        return imgs, evaluated / rays

    def timed(k: int, mode: str) -> float:
        r.num_samples = r.view_samples = k
        r.stop_transmittance = stop if mode == "march" else 0.0
        out = []
        for _ in range(reps):
            t0 = time.perf_counter()
            for v in vs:
                r.render_chunked(v, chunk=chunk, with_normals=False)
            out.append((time.perf_counter() - t0) / len(vs))
        return statistics.median(out)

    with torch.no_grad():
        ref, _ = render(REFERENCE_SAMPLES, "dense")
        rows = []
        for mode in ("dense", "march"):
            for k in samples:
                imgs, per_ray = render(k, mode)  # also the warm-up
                secs = timed(k, mode)
                val = statistics.fmean(float(psnr(a, b)) for a, b in zip(imgs, ref))
                rows.append({"mode": mode, "samples": k, "seconds": secs, "psnr": val, "evaluated_per_ray": per_ray})
                log.info("%s K=%d: %.3f s/view, %.2f dB vs K=%d, %.1f evaluations/ray", mode, k, secs, val,
                         REFERENCE_SAMPLES, per_ray)
    occupied = r.occupied_fraction
    return {"rows": rows, "height": sc.height, "width": sc.width, "views": len(vs), "chunk": chunk,
            "stop_transmittance": stop, "occupied": occupied, "backbone": scene.cfg.backbone.name,
            "encoding": scene.cfg.encoding.name}


def report(results: dict[str, dict], info: dict[str, Any], cmd: str, quick: bool, notes: list[str]) -> str:
    body = [
        "No-grad render of held-out views of the trained reconstruction (the pipeline's default: "
        "VolSDF + grid) at the capture's resolution, colour only (`with_normals=False`, as the stylization's "
        f"first pass and the videos), chunks of `render.chunk` rays. PSNR against a {REFERENCE_SAMPLES}-sample "
        "dense render of the same views. `dense`: every section evaluated in one pass "
        "(`render.stop_transmittance=0`); `march`: early ray termination at the default "
        "`render.stop_transmittance`, rays that miss the occupancy grid skipped. "
        f"Goal: a 270x480 selfie view in <= {TARGET_SECONDS} s at >= {TARGET_PSNR:.0f} dB.",
        "",
    ]
    for name, res in results.items():
        body += [f"### {name} ({res['width']}x{res['height']}, {res['views']} held-out views, "
                 f"{res['backbone']} + {res['encoding']}, occupancy grid {100 * (res['occupied'] or 1):.0f}% "
                 f"occupied, stop_transmittance {res['stop_transmittance']:g})", ""]
        dense = {row["samples"]: row for row in res["rows"] if row["mode"] == "dense"}
        rows = []
        for row in res["rows"]:
            base = dense.get(row["samples"])
            speedup = base["seconds"] / row["seconds"] if base and row["mode"] == "march" else None
            meets = row["seconds"] <= TARGET_SECONDS and row["psnr"] >= TARGET_PSNR
            rows.append([row["mode"], row["samples"], common.fmt(row["seconds"], ".3f"), common.fmt(row["psnr"]),
                         common.fmt(row["evaluated_per_ray"], ".1f"), common.fmt(speedup, ".2f"),
                         "yes" if meets else "no"])
        body += common.md_table(["mode", "samples/ray", "s / view", f"PSNR vs K={REFERENCE_SAMPLES} (dB)",
                                 "field evaluations / ray", "speed-up vs dense", "meets goal"], rows, "lrrrrrc")
        body.append("")
    body += [f"{n}  " for n in notes]
    return common.section(NAME, "Rendering: no-grad view time versus fidelity at the paper's resolution", cmd,
                          info, body, quick)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    p.add_argument("--samples", type=int, nargs="+", default=[8, 12, 16, 24, 32])
    p.add_argument("--views", type=int, default=3, help="held-out views rendered per configuration")
    p.add_argument("--reps", type=int, default=3, help="timed repetitions (median)")
    p.add_argument("--out-root", type=Path, default=ROOT / "outputs" / "benchmarks" / "stylization_quality",
                   help="output_root of the reconstructions (shared with stylization_quality.py)")
    p.add_argument("--override", nargs="*", default=[], help="extra Hydra overrides")
    p.add_argument("--note", nargs="*", default=[], help="lines added to the section (e.g. a figure of an "
                   "earlier version measured in the same session)")
    common.add_common_args(p)
    args = p.parse_args(argv)
    info = common.start_logging(log)
    extra = [*(QUICK if args.quick else []), *args.override, f"output_root={args.out_root}"]
    shared = common.shared_data()
    results = {}
    for name in args.scenes:
        ov = [o.format(shared=shared) for o in SCENES[name]] + extra
        scene, state = trained_scene(ov)
        results[name] = measure(scene, state, args.samples, 1 if args.quick else args.views,
                                1 if args.quick else args.reps)
    common.finish(args, NAME, report(results, info, common.command("render_speed.py", argv), args.quick,
                                           args.note))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
