"""The strength dial and style mixing, measured on finished stylizations of one source.

For every stylization run given (default: those of the main-job benchmark, ``benchmarks/main_job.py``,
which stylizes the shipped head toward three prompts from one reconstruction), at each strength s:

* the independent judge's mean target probability and top-5 hits on the run's held-out views
  (the views of its ``metrics.json``), rendered at the run's resolution; the Spearman rank
  correlation of the probability with s (target >= 0.9) and whether s = 1.25 scores >= s = 1;
* exactness at the ends: PSNR of s = 0 against the source run's own render (target >= 40 dB) and
  of s = 1 against the run's own render (target >= 50 dB), same cameras and render settings;
* view consistency: the warping error between neighbouring frames of a short orbit (as the
  stylization's video measures it), relative to the source's;
* geometry: mean |displacement| of the blended field's mesh from the source mesh (world units);
* the cost of the dial: switching the strength of a loaded run and rendering one 256 px view;
* other parameterizations past s = 1 (:data:`PARTS`): the shape and the colour net at different strengths;
* with ``--vs-training PROMPT``: the dial against the training's own snapshots of the same judge score.

Then a 50/50 mix of the first two runs: both targets' probabilities (they should lie between the
source and each pure run). Pictures for the docs: a strength strip (``docs/images/strength_strip.png``)
and source | A | mix | B (``docs/images/mix.png``). The README's gallery comes from ``docs/make_gallery.py``.

    python -m benchmarks strength                                   # the main-job benchmark's runs
    python -m benchmarks strength --runs outputs/stylizations/A outputs/stylizations/B
    python -m benchmarks strength --vs-training "brain coral" --vs-training-only --out-root ROOT
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common

log = logging.getLogger("bench.strength")
NAME = "strength"
STRENGTHS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5)
STRIP = (0.0, 0.5, 1.0, 1.5)
ORBIT_FRAMES = 8
IMAGES = ROOT / "docs" / "images"


def render_raw(run: Any, view: int, resolution: int | None = None) -> dict[str, torch.Tensor]:
    """rgb [H,W,3], depth [H,W], opacity [H,W] (floats) of capture view ``view`` at the run's resolution."""
    return render_camera(run, run.camera(view, resolution))


@torch.no_grad()
def render_camera(run: Any, rp: Any, i: int = 0) -> dict[str, torch.Tensor]:
    from nerfart_plugin.data.rays import camera_batch

    cams = run.cameras
    batch = camera_batch(rp.K[i], rp.c2w[i], rp.height, rp.width, float(cams.near.min()), float(cams.far.max()),
                         cams.ndc)
    batch = {k: v.to(run.device) if torch.is_tensor(v) else v for k, v in batch.items()}
    out = run.renderer.render_chunked(batch, chunk=run.config.render.chunk, with_normals=False)
    H, W = rp.height, rp.width
    return {"rgb": out["rgb"].reshape(H, W, 3).clamp(0, 1).cpu(), "depth": out["depth"].reshape(H, W).cpu(),
            "opacity": out["opacity"].reshape(H, W).cpu()}


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


def judge_of(run: Any, judge: Any, target: int, views: Sequence[int]) -> dict[str, Any]:
    imgs = torch.stack([render_raw(run, v)["rgb"].permute(2, 0, 1) for v in views])
    a = judge.assess(imgs, target)
    return {"p": a["mean_target_prob"], "top5": sum(1 for v in a["per_view"] if v["target_rank"] < 5),
            "images": imgs}


#: other parameterizations of the dial past the trained style, as (strength of the shape's tensors, strength of the
#: colour net's) at s: below s = 1 they equal the shipped dial (both at s)
PARTS = {"shape capped at 1, colour at s": lambda s: (min(s, 1.0), s),
         "shape at s, colour capped at 1": lambda s: (s, min(s, 1.0))}


def with_state(run: Any, state: dict[str, torch.Tensor], refresh_grid: bool = False, **changes: Any) -> Any:
    """A Run like ``run`` rendering a copy of its renderer holding ``state`` (its occupancy grid estimated afresh
    when ``refresh_grid``); ``changes``: other Run fields (e.g. ``weights``)."""
    import copy
    from dataclasses import replace

    from nerfart_plugin.results.blend import refresh_occupancy

    renderer = copy.deepcopy(run.renderer)
    renderer.load_state_dict(state)
    if refresh_grid:
        refresh_occupancy(renderer)
    return replace(run, renderer=renderer.eval(), **changes)


def part_blend(run: Any, s_shape: float, s_colour: float) -> Any:
    """``run`` with its shape's tensors (all but the colour net's: what ``stylize.freeze_geometry`` freezes) at
    strength ``s_shape`` and its colour net's at ``s_colour``, the occupancy grid re-estimated: a Run."""
    from nerfart_plugin.results.blend import blend_states

    colour = {id(p) for p in run.renderer.field.color_parameters()}
    colour_names = {n for n, p in run.renderer.named_parameters() if id(p) in colour}
    src, sty = run.source.renderer.state_dict(), run.renderer.state_dict()
    shape_blend, colour_blend = blend_states(src, [sty], [s_shape]), blend_states(src, [sty], [s_colour])
    state = {k: colour_blend[k] if k in colour_names else v for k, v in shape_blend.items()}
    return with_state(run, state, refresh_grid=True, weights=(s_colour,))


def part_curves(run: Any, judge: Any, target: int, views: Sequence[int], shipped: Sequence[dict[str, Any]]
                ) -> dict[str, list[float]]:
    """The judge's P(target) at every strength under each of :data:`PARTS` (below s = 1: the shipped dial's)."""
    curves = {}
    for name, split in PARTS.items():
        curves[name] = [c["p"] if c["s"] <= 1.0 else judge_of(part_blend(run, *split(c["s"])), judge, target, views)["p"]
                        for c in shipped]
    return curves


def consistency(run: Any) -> float | None:
    """Mean warping error between neighbouring frames of a short orbit (the video's measure)."""
    from nerfart_plugin.objectives.evaluation import view_consistency

    rp = run.camera_path("orbit", ORBIT_FRAMES, 128)
    frames = [render_camera(run, rp, i) for i in range(len(rp))]
    K = torch.as_tensor(rp.K[0], dtype=torch.float32)
    c2ws = torch.as_tensor(np.asarray(rp.c2w), dtype=torch.float32)
    return view_consistency([{"rgb": f["rgb"], "depth": f["depth"][..., None], "opacity": f["opacity"][..., None]}
                             for f in frames], K, c2ws)


def displacement(run: Any, source_mesh: Any) -> float:
    from nerfart_plugin.export.compare import compare_meshes

    return float(compare_meshes(run.mesh(128, frame="normalized"), source_mesh, n_samples=20_000)["vertex_mean_abs"])


def measure_run(folder: Path, judge: Any) -> dict[str, Any]:
    from nerfart_plugin.api import open_run
    from nerfart_plugin.guidance.imagenet import imagenet_classes

    run = open_run(folder, device="cpu")
    prompt = run.metrics["prompt"]
    target = imagenet_classes().find(prompt)
    views = list(run.metrics["judge"]["views"])
    source_mesh = run.source.mesh(128, frame="normalized")
    exact_source = psnr(render_raw(run.with_strength(0.0), views[0])["rgb"], render_raw(run.source, views[0])["rgb"])
    exact_run = psnr(render_raw(run.with_strength(1.0), views[0])["rgb"], render_raw(run, views[0])["rgb"])
    rows = []
    for s in STRENGTHS:
        t0 = time.perf_counter()
        blended = run.with_strength(s)
        j = judge_of(blended, judge, target, views)
        rows.append({"s": s, "p": j["p"], "top5": j["top5"], "consistency": consistency(blended),
                     "displacement": displacement(blended, source_mesh), "seconds": time.perf_counter() - t0})
        log.info("%s s=%.2f: P=%.4f top-5 %d/%d", prompt, s, j["p"], j["top5"], len(views))
    t0 = time.perf_counter()
    run.with_strength(0.5).render(views[0], resolution=256)
    switch = time.perf_counter() - t0
    return {"folder": str(folder), "prompt": prompt, "views": views, "exact_source_db": exact_source,
            "exact_run_db": exact_run, "curve": rows, "switch_render_256_s": switch,
            "source_consistency": consistency(run.source), "parts": part_curves(run, judge, target, views, rows)}


# --------------------------------------------------------------------------- the dial versus training
#: the dial's strengths matched against the training's own snapshots
VS_TRAINING_STRENGTHS = (0.5, 0.75)


def snapshot_overrides(prompt: str, out_root: Path) -> list[str]:
    """The stylization of ``prompt`` at the defaults (``guidance=imagenet``) into ``out_root`` (which holds the
    reconstruction), its video and meshes skipped (no trained tensor changes)."""
    return ["guidance=imagenet", f"prompt={json.dumps(prompt)}", f"output_root={out_root}", "stylize.video_frames=0",
            "export.enabled=false"]


def train_with_snapshots(overrides: Sequence[str], every: int) -> tuple[Path, dict[int, dict[str, torch.Tensor]]]:
    """The stylization ``overrides`` describe (:func:`snapshot_overrides`), trained with the renderer's tensors kept
    every ``every`` steps. Returns the run folder and the snapshots by step."""
    import lightning as L

    from nerfart_plugin.run.pipeline import run as run_pipeline
    from nerfart_plugin.run.stages.stylize import StylizeStage

    snapshots: dict[int, dict[str, torch.Tensor]] = {}

    class Snapshots(L.Callback):
        def on_train_batch_end(self, trainer: Any, module: Any, *args: Any) -> None:
            if trainer.global_step % every == 0:
                snapshots[trainer.global_step] = {k: v.detach().clone() for k, v in module.renderer.state_dict().items()}

    original = StylizeStage.live_callbacks
    StylizeStage.live_callbacks = lambda self: [*original(self), Snapshots()]  # type: ignore[method-assign]
    try:
        result = run_pipeline(common.compose(list(overrides)))
    finally:
        StylizeStage.live_callbacks = original  # type: ignore[method-assign]
    if not snapshots:
        raise SystemExit(f"--vs-training: the stylization was already finished ({result['stylization']['dir']}), so "
                         "no snapshot was taken; remove its folder or give another --out-root")
    return Path(result["stylization"]["dir"]), snapshots


def source_likeness(run: Any, views: Sequence[int]) -> dict[str, float]:
    """How much of the source a field keeps on the held-out views: PSNR and edge similarity to the source render."""
    from nerfart_plugin.objectives.evaluation import edge_similarity

    mine = torch.stack([render_raw(run, v)["rgb"].permute(2, 0, 1) for v in views])
    src = torch.stack([render_raw(run.source, v)["rgb"].permute(2, 0, 1) for v in views])
    return {"psnr_to_source": psnr(mine, src), "edges_to_source": edge_similarity(mine, src)}


def dial_vs_training(prompt: str, overrides: Sequence[str], judge: Any, every: int = 10) -> dict[str, Any]:
    """The dial at :data:`VS_TRAINING_STRENGTHS` against the training snapshot whose judge score is closest (in log
    probability): the judge, how much of the source each keeps, view consistency and mesh displacement."""
    import math

    from nerfart_plugin.api import open_run
    from nerfart_plugin.guidance.imagenet import imagenet_classes

    folder, snapshots = train_with_snapshots(overrides, every)
    run = open_run(folder, device="cpu")
    target, views = imagenet_classes().find(prompt), list(run.metrics["judge"]["views"])
    source_mesh = run.source.mesh(128, frame="normalized")

    trained = {step: judge_of(with_state(run, state), judge, target, views)["p"]
               for step, state in sorted(snapshots.items())}

    def facts(field: Any, p: float) -> dict[str, Any]:
        return {"p": p, **source_likeness(field, views), "consistency": consistency(field),
                "displacement": displacement(field, source_mesh)}

    pairs = []
    for s in VS_TRAINING_STRENGTHS:
        dial = run.with_strength(s)
        p = judge_of(dial, judge, target, views)["p"]
        step = min(trained, key=lambda k: abs(math.log(trained[k]) - math.log(p)))
        pairs.append({"s": s, "step": step, "dial": facts(dial, p), "training": facts(with_state(run, snapshots[step]),
                                                                                    trained[step])})
        log.info("dial s=%.2f (P %.4f) vs training step %d (P %.4f)", s, p, step, trained[step])
    return {"prompt": prompt, "folder": str(folder), "steps": max(trained), "trained_p": trained,
            "source_consistency": consistency(run.source), "pairs": pairs}


def vs_training_lines(v: dict[str, Any]) -> list[str]:
    f = common.fmt
    rows = []
    for pair in v["pairs"]:
        for name, d in (("dial", pair["dial"]), ("training", pair["training"])):
            label = f"dial s = {pair['s']:g}" if name == "dial" else f"training, step {pair['step']} of {v['steps']}"
            ratio = d["consistency"] / v["source_consistency"] if d["consistency"] and v["source_consistency"] else None
            rows.append([label, f"{d['p']:.4f}", f(d["psnr_to_source"], ".2f"), f(d["edges_to_source"], ".3f"),
                         f(ratio, ".2f"), f(d["displacement"], ".4f")])
    curve = ", ".join(f"{k}: {p:.4f}" for k, p in sorted(v["trained_p"].items(), key=lambda kv: int(kv[0])))
    return [f"### The dial versus training ({v['prompt']})", "",
            "The same stylization trained again at the defaults with its tensors kept every few steps; each dial "
            "strength is set beside the training step whose judge score is closest (log probability). Keeping the "
            "source: PSNR and edge similarity of the held-out views to the source render (higher keeps more).", "",
            *common.md_table(["field", "judge P(target)", "PSNR to source (dB)", "edge similarity to source",
                              "view-consistency ratio", "mean abs displacement"], rows), "",
            f"Judge P(target) along training (step: P): {curve}.", ""]


def spearman(xs: Sequence[float], ys: Sequence[float]) -> float:
    from scipy.stats import spearmanr

    return float(spearmanr(xs, ys).statistic)


def measure_mix(a_dir: Path, b_dir: Path, judge: Any) -> dict[str, Any]:
    from nerfart_plugin.api import mix, open_run
    from nerfart_plugin.guidance.imagenet import imagenet_classes
    from nerfart_plugin.utils.images import save_image, side_by_side

    a, b = open_run(a_dir, device="cpu"), open_run(b_dir, device="cpu")
    half = mix([a, b], [0.5, 0.5])
    views = list(a.metrics["judge"]["views"])
    prompts = [a.metrics["prompt"], b.metrics["prompt"]]
    out: dict[str, Any] = {"prompts": prompts, "p": {}}
    for key, run in (("source", a.source), ("a", a), ("mix", half), ("b", b)):
        out["p"][key] = {which: judge_of(run, judge, imagenet_classes().find(prompt), views)["p"]
                         for which, prompt in zip(("p_a", "p_b"), prompts)}
    pics = [render_raw(r, views[1])["rgb"].numpy() for r in (a.source, a, half, b)]
    IMAGES.mkdir(parents=True, exist_ok=True)
    left = side_by_side(pics[0], pics[1], labels=("source", prompts[0]))
    right = side_by_side(pics[2], pics[3], labels=("50/50 mix", prompts[1]))
    save_image(side_by_side(left, right, labels=None), IMAGES / "mix.png")
    return out


def strength_strip(folder: Path) -> None:
    """``docs/images/strength_strip.png``: one held-out view of the run at the strengths of :data:`STRIP`."""
    from nerfart_plugin.api import open_run
    from nerfart_plugin.utils.images import image_grid, label_image, save_image, to_uint8

    run = open_run(folder, device="cpu")
    view = run.metrics["judge"]["views"][1]
    tiles = [label_image(to_uint8(render_raw(run.with_strength(s), view)["rgb"]), f"s = {s:g}") for s in STRIP]
    IMAGES.mkdir(parents=True, exist_ok=True)
    save_image(image_grid(tiles, ncols=len(tiles)), IMAGES / "strength_strip.png")


# --------------------------------------------------------------------------- report
def report(raw: dict[str, Any], info: dict[str, Any], cmd: str, notes: Sequence[str] = ()) -> str:
    body = ["Each stylization run at strengths s (θ = θ_src + s·(θ_run − θ_src), the occupancy grid re-estimated "
            "for the blended field): the independent judge (EfficientNet-Lite2) on the run's held-out views at "
            "its resolution, the warping error along an 8-frame 128 px orbit relative to the source's, and the "
            "mean |displacement| of the blended field's 128^3 mesh from the source mesh (normalized units).", ""]
    verdicts = []
    for r in raw["runs"]:
        curve = r["curve"]
        rho = spearman([c["s"] for c in curve], [c["p"] for c in curve])
        p1 = next(c["p"] for c in curve if c["s"] == 1.0)
        p125 = next(c["p"] for c in curve if c["s"] == 1.25)
        body += [f"### {r['prompt']}", ""]
        rows = [[f"{c['s']:g}", f"{c['p']:.4f}", f"{c['top5']}/{len(r['views'])}",
                 common.fmt(None if c["consistency"] is None or not r["source_consistency"]
                            else c["consistency"] / r["source_consistency"]),
                 f"{c['displacement']:.4f}"] for c in curve]
        body += common.md_table(["s", "judge P(target)", "top-5 views", "view-consistency ratio",
                                 "mean abs displacement"], rows)
        body += ["", f"Spearman(s, P) = {rho:.2f}; s = 0 vs the source render {r['exact_source_db']:.1f} dB, s = 1 "
                     f"vs the run's render {r['exact_run_db']:.1f} dB; switching the strength and rendering one 256 px "
                     f"view: {r['switch_render_256_s']:.2f} s.", ""]
        verdicts.append(f"- {r['prompt']}: Spearman >= 0.9 **{'MET' if rho >= 0.9 else 'NOT MET'}** ({rho:.2f}); "
                        f"s = 1.25 >= s = 1 **{'MET' if p125 >= p1 else 'NOT MET'}**; s = 0 >= 40 dB "
                        f"**{'MET' if r['exact_source_db'] >= 40 else 'NOT MET'}**; s = 1 >= 50 dB "
                        f"**{'MET' if r['exact_run_db'] >= 50 else 'NOT MET'}**; switch + 256 px render <= 1 s "
                        f"**{'MET' if r['switch_render_256_s'] <= 1 else 'NOT MET'}** ({r['switch_render_256_s']:.2f} s)")
    parts = [r for r in raw["runs"] if r.get("parts")]
    if parts:
        body += ["### Other parameterizations past the trained style", "",
                 "The shape's tensors (grid and geometry net) and the colour net's at different strengths past s = 1 "
                 "(below 1 both follow s, as the shipped dial): the judge's P(target) at s = 1, 1.25, 1.5 and the "
                 "Spearman correlation over all s.", ""]
        rows = []
        for r in parts:
            ps = {c["s"]: c["p"] for c in r["curve"]}
            curves = {"shipped: both at s": [c["p"] for c in r["curve"]], **r["parts"]}
            for name, curve in curves.items():
                at = dict(zip(ps, curve))
                rows.append([r["prompt"], name, *(f"{at[s]:.4f}" for s in (1.0, 1.25, 1.5)),
                             f"{spearman(list(ps), curve):.2f}"])
        body += common.md_table(["run", "parameterization", "P at s = 1", "s = 1.25", "s = 1.5", "Spearman"], rows)
        body += [""]
    mix = raw.get("mix")
    if mix:
        (pa, pb), m = mix["prompts"], mix["p"]
        body += [f"### Mixing {pa} and {pb} 50/50", ""]
        names = {"source": "source", "a": f"{pa} (run)", "mix": "50/50 mix", "b": f"{pb} (run)"}
        body += common.md_table(["field", f"P({pa})", f"P({pb})"],
                                [[names[k], f"{m[k]['p_a']:.4f}", f"{m[k]['p_b']:.4f}"] for k in names])
        between = all(min(m["source"][p], m[k][p]) <= m["mix"][p] <= max(m["source"][p], m[k][p])
                      for p, k in (("p_a", "a"), ("p_b", "b")))
        verdicts.append(f"- the mix's two target probabilities lie between the source and each pure run: "
                        f"**{'MET' if between else 'NOT MET'}**")
        body += ["", "![source | A | mix | B](docs/images/mix.png)", ""]
    if raw.get("vs_training"):
        body += vs_training_lines(raw["vs_training"])
    body += ["![strength strip](docs/images/strength_strip.png)", "", "**Targets**", "", *verdicts]
    body += ["", *notes] if notes else []
    return common.section(NAME, "The strength dial and style mixing (head)", cmd, info, body, False)


def default_runs() -> list[Path]:
    return sorted((ROOT / "outputs" / "benchmarks" / "main_job" / "stylizations").glob("*"))


def measure(folders: Sequence[Path]) -> dict[str, Any]:
    """The curve of every finished run, the mix of the first two, and their pictures."""
    from nerfart_plugin.objectives.evaluation import ImageNetJudge

    runs = [r for r in folders if (r / "final.ckpt").is_file()]
    if not runs:
        raise SystemExit("no finished stylization runs: run benchmarks/main_job.py first, or pass --runs")
    judge = ImageNetJudge()
    raw: dict[str, Any] = {"runs": [measure_run(r, judge) for r in runs]}
    if len(runs) >= 2:
        raw["mix"] = measure_mix(runs[0], runs[1], judge)
    strength_strip(runs[0])
    return raw


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", nargs="+", type=Path, default=None, help="stylization folders of one source")
    p.add_argument("--vs-training", metavar="PROMPT", default=None, help="also train PROMPT's stylization again into "
                   "--out-root (which holds the reconstruction) with snapshots, and set the dial beside training")
    p.add_argument("--vs-training-only", action="store_true", help="only that study, added to the raw file's runs")
    p.add_argument("--out-root", type=Path, default=ROOT / "outputs" / "benchmarks" / "main_job")
    p.add_argument("--note", nargs="*", default=[], help="lines added to the report (e.g. the commands that measured "
                   "what --report-only reports)")
    common.add_raw_args(p)
    common.add_common_args(p)
    args = p.parse_args(argv)
    info = common.start_logging(log)
    def measure_all() -> dict[str, Any]:
        if args.vs_training_only:
            raw = json.loads(Path(args.raw or common.raw_path(NAME, args.quick)).read_text())
        else:
            raw = measure(args.runs or default_runs())
        if args.vs_training:
            from nerfart_plugin.objectives.evaluation import ImageNetJudge

            raw["vs_training"] = dial_vs_training(args.vs_training, snapshot_overrides(args.vs_training, args.out_root),
                                                  ImageNetJudge())
        return raw

    raw = common.raw_results(args, NAME, measure_all)
    common.finish(args, NAME, report(raw, info, common.command("strength.py", argv or sys.argv[1:]), args.note))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
