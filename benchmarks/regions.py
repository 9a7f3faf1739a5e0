"""Stylizing only a part: regions on the shipped head (outside unchanged, the style inside, seams, cost, two styles).

On one reconstruction of the shipped head (the main job's settings, ``guidance=imagenet``), for each prompt the
whole-scene stylization and one inside each region: a box around the head and one around the shoulders, both
read off the source's surface along the capture's up direction (:func:`region_boxes`). For each regional run:

* outside: the held-out pixels whose rays stay clear of the region (and of the occupancy cells it reaches) against
  the source's render, PSNR (target >= 40 dB), from the run's ``metrics.json``; the mesh vertices farther than
  the feather and margin from the region, their largest distance to the source surface over the scene's size
  (target <= 1e-3);
* inside: the judge's target probability and top-5 rate on each held-out view's crop of the region's projection,
  the gain over the source's crop as a share of the whole-scene run's gain on the same crops (target >= 0.8);
* seams: the image gradient (Sobel, luma) in the feather band over the gradient inside the region, on the
  stylized held-out views (the seam measure; target <= 1), beside the source's own ratio;
* cost: the regional stylization's fit time over the whole-scene one's (target <= 1.2);

then two styles on the two regions of the source (the first prompt's head run and the second's shoulders run,
mixed region by region): each region's crop should favour its own prompt. The picture source | whole-scene |
regional | two regions goes to ``docs/images/regions.png``.

    python -m benchmarks regions --out-root /tmp/regions                  # trains what is missing, then measures
    python -m benchmarks regions --out-root /tmp/regions --report-only     # the section from the raw file
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from benchmarks import common

ROOT = Path(__file__).resolve().parents[1]
log = logging.getLogger("bench.regions")
NAME = "regions"
PROMPTS = ("brain coral", "jack-o'-lantern", "tabby")
IMAGES = ROOT / "docs" / "images"
#: the head: the surface above this share of its height along up; the shoulders: below the lower share
HEAD_FROM, SHOULDERS_TO = 0.52, 0.38
#: the boxes' feather and the geometry's margin, as shares of the surface's height
FEATHER_SHARE, MARGIN_SHARE = 0.03, 0.03
SETTINGS = ("guidance=imagenet",)


# ---------------------------------------------------------------------- the regions
def region_boxes(source: Any) -> dict[str, Any]:
    """The head and shoulders boxes (world units) of a reconstruction Run: its surface (marching cubes) split
    along the capture's up direction at :data:`HEAD_FROM` / :data:`SHOULDERS_TO` of its height, each part's
    extent in the up-aligned frame."""
    from nerfart_plugin.api import Region

    mesh = source.mesh(resolution=128, frame="world")
    world = source.cameras.to_world(np.asarray(source.cameras.c2w)[:, :3, :4])
    up = -world[:, :3, 1].mean(0)
    up /= np.linalg.norm(up)
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    R = np.stack([side, up, np.cross(side, up)], 1)  # columns: the box's axes in the world
    local = np.asarray(mesh.vertices) @ R
    h = local[:, 1]
    lo, hi = float(h.min()), float(h.max())
    height = hi - lo
    feather, margin = FEATHER_SHARE * height, MARGIN_SHARE * height
    out = {}
    for name, keep in (("head", h >= lo + HEAD_FROM * height), ("shoulders", h <= lo + SHOULDERS_TO * height)):
        part = local[keep]
        centre_local = 0.5 * (part.min(0) + part.max(0))
        half = 0.5 * (part.max(0) - part.min(0)) + margin
        out[name] = Region.box(R @ centre_local, half, rotation=R, feather=feather).with_margin(margin)
    return {"regions": out, "height": height, "feather": feather, "margin": margin,
            "diagonal": float(np.linalg.norm(np.asarray(mesh.bounds[1]) - np.asarray(mesh.bounds[0])))}


# ---------------------------------------------------------------------- training
def train(root: Path, prompt: str, region_file: Path | None) -> Path:
    """The stylization of ``prompt`` (inside ``region_file``; None: the whole scene), trained or reused."""
    region = [f"region={region_file}"] if region_file is not None else []
    return common.trained_run(root, [*SETTINGS, f"+prompt={json.dumps(prompt)}", *region])


# ---------------------------------------------------------------------- measuring
def batches(run: Any, ids: Sequence[int], resolution: int) -> list[dict[str, Any]]:
    from nerfart_plugin.data.rays import camera_batch

    out = []
    for i in ids:
        rp = run.camera(int(i), resolution)
        cams = run.cameras
        b = camera_batch(rp.K[0], rp.c2w[0], rp.height, rp.width, float(cams.near.min()), float(cams.far.max()),
                         cams.ndc)
        out.append({k: v.to(run.device) if torch.is_tensor(v) else v for k, v in b.items()})
    return out


@torch.no_grad()
def renders(run: Any, views: Sequence[dict[str, Any]]) -> tuple[torch.Tensor, list[dict[str, torch.Tensor]]]:
    """[B,3,H,W] images of ``views`` and the raw outputs (depth, opacity)."""
    outs = [run.renderer.render_chunked(v, chunk=run.config.render.chunk, with_normals=False) for v in views]
    imgs = torch.stack([o["rgb"].reshape(v["H"], v["W"], 3).permute(2, 0, 1).clamp(0, 1) for o, v in zip(outs, views)])
    return imgs.cpu(), outs


def sobel(img: torch.Tensor) -> torch.Tensor:
    """[H,W] gradient magnitude of an image [3,H,W]'s luma."""
    luma = (img * torch.tensor([0.299, 0.587, 0.114])[:, None, None]).sum(0)[None, None]
    kx = torch.tensor([[-1.0, 0, 1], [-2, 0, 2], [-1, 0, 1]])[None, None] / 8
    gx, gy = F.conv2d(luma, kx, padding=1), F.conv2d(luma, kx.transpose(-1, -2), padding=1)
    return (gx.square() + gy.square()).sqrt()[0, 0]


def seam_ratio(img: torch.Tensor, colour_mask: torch.Tensor, opacity: torch.Tensor) -> float | None:
    """Mean gradient in the feather band (colour mask in (0.02, 0.98) on the surface) over the mean inside
    (mask >= 0.98): 1 means the band is no busier than the region itself."""
    g = sobel(img)
    on = opacity > 0.5
    band, inside = on & (colour_mask > 0.02) & (colour_mask < 0.98), on & (colour_mask >= 0.98)
    if int(band.sum()) < 10 or int(inside.sum()) < 10:
        return None
    return float(g[band].mean() / g[inside].mean().clamp_min(1e-8))


def surface_masks(mask: Any, views: Sequence[dict[str, Any]], outs: Sequence[dict[str, Any]]) -> list[torch.Tensor]:
    """The region's colour mask at each pixel's rendered surface point [H,W]."""
    out = []
    for v, o in zip(views, outs):
        colour, _ = mask(v["rays_o"] + v["rays_d"] * o["depth"].reshape(-1, 1))
        out.append(colour.reshape(v["H"], v["W"]).cpu())
    return out


def mesh_outside(run_folder: Path, region: Any, cams: Any, reach: float, diagonal: float) -> dict[str, Any]:
    """The stylized mesh's vertices farther than ``reach`` (world units) from the region (its mask 0 there, the
    region grown by ``reach``): their largest and mean distance to the source surface, over the scene's size."""
    import trimesh

    from nerfart_plugin.export.compare import SurfaceDistance

    mesh_dir = run_folder / "mesh"
    source = trimesh.load(mesh_dir / "source.ply", force="mesh", process=False)
    stylized = trimesh.load(next(mesh_dir.glob("stylized*.ply")), force="mesh", process=False)
    v = np.asarray(stylized.vertices)
    grown = region.with_margin(0.0)
    far = np.ones(len(v), dtype=bool)
    for off in np.stack(np.meshgrid(*[[-reach, 0.0, reach]] * 3, indexing="ij"), -1).reshape(-1, 3):
        far &= grown.mask(v + off, reach) == 0
    if not far.any():
        return {"vertices_outside": 0}
    d = SurfaceDistance(source).query(v[far])
    return {"vertices_outside": int(far.sum()), "max_over_size": float(d.max() / diagonal),
            "mean_over_size": float(d.mean() / diagonal)}


def judge_crops(prompt: str, mask: Any, views: Sequence[dict[str, Any]], source: torch.Tensor,
                stylized: torch.Tensor, ids: Sequence[int]) -> dict[str, Any]:
    from nerfart_plugin.objectives.evaluation import region_metrics

    dev_views = [{k: (val.cpu() if torch.is_tensor(val) else val) for k, val in v.items()} for v in views]
    return region_metrics(prompt, mask.to("cpu"), dev_views, source, stylized, list(ids))["judge_inside"]


def measure_prompt(prompt: str, folders: dict[str, Path], regions: dict[str, Any], geometry: dict[str, Any]
                   ) -> dict[str, Any]:
    from nerfart_plugin.api import open_run

    whole = open_run(folders["whole"], device="cpu")
    ids = whole.metrics["judge"]["views"]
    res = whole.resolution
    views = batches(whole, ids, res)
    src_imgs, src_outs = renders(_stylization_sampling(whole, 0.0), views)
    whole_imgs, _ = renders(whole, views)
    out: dict[str, Any] = {"prompt": prompt, "views": ids, "whole": {"folder": str(folders["whole"]),
                                                                      "fit_s": whole.metrics["stage_seconds"]["fit"]}}
    for name in ("head", "shoulders"):
        run = open_run(folders[name], device="cpu")
        mask = run.renderer.field.regions[0]
        imgs, outs = renders(run, views)
        m = run.metrics
        regional = judge_crops(prompt, mask, views, src_imgs, imgs, ids)
        reference = judge_crops(prompt, mask, views, src_imgs, whole_imgs, ids)
        colour = surface_masks(mask, views, outs)
        seams = [seam_ratio(i, c, o["opacity"].reshape(c.shape).cpu()) for i, c, o in zip(imgs, colour, outs)]
        src_seams = [seam_ratio(i, c, o["opacity"].reshape(c.shape).cpu()) for i, c, o in zip(src_imgs, colour, src_outs)]
        reach = geometry["feather"] + geometry["margin"]
        out[name] = {
            "folder": str(folders[name]), "fit_s": m["stage_seconds"]["fit"],
            "cost_ratio": m["stage_seconds"]["fit"] / out["whole"]["fit_s"],
            "outside_psnr": m["region"]["outside_psnr_to_source"], "outside_max_change": m["region"]["outside_max_change"],
            "covered_share": m["region"]["covered_share"],
            "mesh": mesh_outside(Path(folders[name]), regions[name], run.cameras, reach, geometry["diagonal"]),
            "judge_regional": _brief(regional), "judge_whole": _brief(reference),
            "gain_share": _share(regional, reference),
            "seam": _mean(seams), "seam_source": _mean(src_seams),
        }
        log.info("%s / %s: outside %.1f dB, gain share %s, seam %s, cost %.2fx", prompt, name,
                 out[name]["outside_psnr"], common.fmt(out[name]["gain_share"]), common.fmt(out[name]["seam"]),
                 out[name]["cost_ratio"])
    return out


def _stylization_sampling(run: Any, strength: float) -> Any:
    """The source rendered with the stylization's sampling settings (its dial at 0), as its metrics compare."""
    return run.with_strength(strength)


def _brief(block: dict[str, Any]) -> dict[str, Any]:
    if "stylized" not in block:
        return {"skipped": block.get("skipped")}
    return {"p_source": block["source"]["mean_target_prob"], "p": block["stylized"]["mean_target_prob"],
            "top5_source": block["source"]["top5_rate"], "top5": block["stylized"]["top5_rate"],
            "gain": block["gain_mean_target_prob"]}


def _share(regional: dict[str, Any], whole: dict[str, Any]) -> float | None:
    if "stylized" not in regional or "stylized" not in whole or whole["gain_mean_target_prob"] <= 0:
        return None
    return regional["gain_mean_target_prob"] / whole["gain_mean_target_prob"]


def _mean(values: Sequence[float | None]) -> float | None:
    kept = [v for v in values if v is not None]
    return float(np.mean(kept)) if kept else None


def two_styles(prompts: Sequence[str], folders: dict[str, dict[str, Path]]) -> dict[str, Any]:
    """The first prompt's head run and the second's shoulders run mixed region by region: the judge on each
    region's crops, for both prompts."""
    from nerfart_plugin.api import mix, open_run
    from nerfart_plugin.objectives.evaluation import region_metrics

    a, b = prompts[0], prompts[1]
    head, shoulders = open_run(folders[a]["head"], device="cpu"), open_run(folders[b]["shoulders"], device="cpu")
    both = mix([head, shoulders], [1.0, 1.0])
    ids = head.metrics["judge"]["views"]
    views = batches(head, ids, head.resolution)
    src, _ = renders(_stylization_sampling(head, 0.0), views)
    imgs, _ = renders(both, views)
    out: dict[str, Any] = {"prompts": [a, b]}
    for region_name, run in (("head", head), ("shoulders", shoulders)):
        mask = run.renderer.field.regions[0]
        cpu_views = [{k: (val.cpu() if torch.is_tensor(val) else val) for k, val in v.items()} for v in views]
        out[region_name] = {p: _brief(region_metrics(p, mask.to("cpu"), cpu_views, src, imgs, ids)["judge_inside"])
                            for p in (a, b)}
    return out


def step_cost(root: Path, prompt: str, region_file: Path, steps: int = 4, rounds: int = 3) -> dict[str, Any]:
    """Seconds per stylization step over the whole scene and inside the region, measured in one process, the
    two interleaved (``rounds`` x ``steps`` steps each; medians): the cost of the composite."""
    import time

    from nerfart_plugin.config.compose import load_config
    from nerfart_plugin.guidance.style import build_style, check_style
    from nerfart_plugin.run.factories import build_scene, build_stylization_system, load_renderer_state
    from nerfart_plugin.run.fit import train_steps
    from nerfart_plugin.run.stages.reconstruct import ReconstructStage

    times: dict[str, list[float]] = {"whole": [], "region": []}
    systems = {}
    for name, extra in (("whole", []), ("region", [f"region={region_file}"])):
        scene = build_scene(load_config([f"output_root={root}", *SETTINGS, f"+prompt={json.dumps(prompt)}", *extra]))
        style = build_style(scene.cfg)
        check_style(style, scene.cfg.stylize.negatives)
        state = load_renderer_state(ReconstructStage(scene).folder.final, scene)
        systems[name] = (scene, build_stylization_system(scene, state, style))
    for _ in range(rounds):
        for name, (scene, system) in systems.items():
            t0 = time.perf_counter()
            train_steps(system, steps, scene.device)
            times[name].append((time.perf_counter() - t0) / steps)
    whole, region = float(np.median(times["whole"])), float(np.median(times["region"]))
    return {"whole_s_per_step": whole, "region_s_per_step": region, "ratio": region / whole, "rounds": rounds,
            "steps": steps}


# ---------------------------------------------------------------------- the picture
def picture(prompts: Sequence[str], folders: dict[str, dict[str, Path]], view: int) -> Path:
    """source | whole-scene | inside the head box | two regions (first prompt on the head, second on the
    shoulders), one held-out view."""
    from nerfart_plugin.api import mix, open_run
    from nerfart_plugin.utils.images import label_image, save_image, side_by_side

    a, b = prompts[0], prompts[1]
    whole, head = open_run(folders[a]["whole"], device="cpu"), open_run(folders[a]["head"], device="cpu")
    both = mix([head, open_run(folders[b]["shoulders"], device="cpu")], [1.0, 1.0])
    res = whole.resolution
    tiles = [(_stylization_sampling(whole, 0.0), "source"), (whole, f"{a}: whole scene"), (head, f"{a}: head only"),
             (both, f"{a} head, {b} shoulders")]
    imgs = [label_image((run.render(view, res)["rgb"]), text) for run, text in tiles]
    row = imgs[0]
    for img in imgs[1:]:
        row = side_by_side(row, img, labels=None)
    return save_image(row, IMAGES / "regions.png")


# ---------------------------------------------------------------------- the report
def measure(root: Path, prompts: Sequence[str]) -> dict[str, Any]:
    from nerfart_plugin.api import open_run

    recon = common.trained_run(root, [*SETTINGS, "stage=reconstruct"])
    geometry = region_boxes(open_run(recon, device="cpu"))
    regions = geometry.pop("regions")
    files = {name: region.save(root / "regions" / f"{name}.npz") for name, region in regions.items()}
    folders = {p: {"whole": train(root, p, None), **{n: train(root, p, f) for n, f in files.items()}} for p in prompts}
    per_prompt = [measure_prompt(p, folders[p], regions, geometry) for p in prompts]
    mixed = two_styles(prompts, folders)
    cost = step_cost(root, prompts[0], files["head"])
    view = per_prompt[0]["views"][0]
    pic = picture(prompts, folders, view)
    return {"reconstruction": str(recon), "geometry": geometry, "region_files": {k: str(v) for k, v in files.items()},
            "prompts": per_prompt, "two_styles": mixed, "step_cost": cost, "picture": str(pic)}


def report(raw: dict[str, Any], info: dict[str, Any], cmd: str) -> str:
    g = raw["geometry"]
    body = [f"Regions read off the source's surface ({g['height']:.3f} world units tall along up): the head above "
            f"{HEAD_FROM:.0%} of its height, the shoulders below {SHOULDERS_TO:.0%}; feather and margin "
            f"{g['feather']:.3f} each. Each run: the main job's settings (`guidance=imagenet`), the same steps "
            "inside a region as over the whole scene.", ""]
    rows = []
    for p in raw["prompts"]:
        for name in ("head", "shoulders"):
            r = p[name]
            mesh = r["mesh"]
            rows.append([p["prompt"], name, common.fmt(r["outside_psnr"], ".1f"), common.fmt(r["outside_max_change"], ".4f"),
                         common.fmt(mesh.get("max_over_size"), ".2e"),
                         f"{common.fmt(r['judge_regional'].get('p'), '.3f')} / {common.fmt(r['judge_whole'].get('p'), '.3f')}",
                         f"{common.fmt(r['judge_regional'].get('top5'), '.2f')} / {common.fmt(r['judge_whole'].get('top5'), '.2f')}",
                         common.fmt(r["gain_share"]), f"{common.fmt(r['seam'])} ({common.fmt(r['seam_source'])})",
                         common.fmt(r["cost_ratio"])])
    body += common.md_table(["prompt", "region", "outside PSNR (dB; 100: identical)", "outside max change",
                             "mesh outside: max move / size", "P(target) on the crop: region / whole",
                             "top-5 on the crop: region / whole", "gain share (>= 0.8)", "seam (source)",
                             "fit time vs whole"], rows)
    t = raw["two_styles"]
    a, b = t["prompts"]
    body += ["", f"Two styles on two regions of the source (`mix([{a} inside the head, {b} inside the shoulders])`), "
             "the judge on each region's crops:", ""]
    body += common.md_table(["region", f"P({a})", f"P({b})", "favours"],
                            [[name, common.fmt(t[name][a].get("p"), ".3f"), common.fmt(t[name][b].get("p"), ".3f"),
                              a if (t[name][a].get("p") or 0) > (t[name][b].get("p") or 0) else b]
                             for name in ("head", "shoulders")])
    c = raw["step_cost"]
    body += ["", f"The cost of the composite, measured in one process ({c['rounds']} x {c['steps']} steps of each, "
             f"interleaved, medians; {raw['prompts'][0]['prompt']}, head region): {c['region_s_per_step']:.2f} s per step "
             f"inside the region against {c['whole_s_per_step']:.2f} s over the whole scene, **{c['ratio']:.2f}x**. "
             "(The fit times of the table ran one after the other on a shared machine; this is the ratio to read.)"]
    body += ["", "Targets: outside >= 40 dB and mesh moves <= 1e-3 of the size; gain share >= 0.8; seam <= 1; cost "
             "<= 1.2x; each region favours its own prompt.", "",
             f"![source | whole scene | head only | two regions]({common.rel(Path(raw['picture']), ROOT)})"]
    return common.section(NAME, "Regions: stylizing only a part of the head", cmd, info, body, False)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out-root", type=Path, default=ROOT / "outputs" / "benchmarks" / "regions")
    p.add_argument("--prompts", nargs="+", default=list(PROMPTS))
    common.add_raw_args(p)
    common.add_common_args(p)
    args = p.parse_args(argv)
    info = common.start_logging(log)
    raw = common.raw_results(args, NAME, lambda: measure(args.out_root, args.prompts))
    common.finish(args, NAME, report(raw, info, common.command("regions.py", argv or sys.argv[1:])))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
