"""Does the preview look like the full run, and does its verdict say whether the full run works?

For each prompt of the study, ``python -m nerfart_plugin stage=preview guidance=imagenet +prompt=...`` runs on the
cached reconstruction in ``--out-root`` (the main-job benchmark's), timed from the command's start (start-up, guide
and judge loading included); then the full stylization of the same prompt at this commit's defaults in the same
root (its video and meshes skipped, which changes no trained result; ``--keep-full`` keeps the raw file's full
runs instead of running them again). Measured per prompt:

* resemblance: of the preview's held-out views (at its strength) to the full run's, where the full run's folder
  is on this machine: SSIM at 128 px and the cosine of the judge's pooled features (EfficientNet-Lite2, its last
  block), beside the same for the source's views (how much closer the preview is than doing nothing);
* the subject: silhouette IoU of the preview with the source (target >= 0.9);
* the verdict (:func:`nerfart_plugin.run.stages.preview.verdict`) against the full run: a run *works* when the
  judge puts the target in its top 5 on at least 3 of its 4 held-out views;
* time per preview (target <= 60 s).

    python -m benchmarks preview --out-root /tmp/mj/out
    python -m benchmarks preview --out-root /tmp/mj/out --keep-full       # the previews again, the full runs kept
    python -m benchmarks preview --out-root /tmp/mj/out --retime          # the same previews, timed again
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Optional

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common

log = logging.getLogger("bench.preview")
NAME = "preview"
PROMPTS = ("brain coral", "jack-o'-lantern", "tabby", "honeycomb", "ski mask", "zebra", "goldfish",
           "jigsaw puzzle", "volcano", "school bus")
#: prompts added afterwards (the study's fifteen with these)
FRESH_PROMPTS = ("strawberry", "snail", "teddy bear", "airliner", "pizza")
#: the full run's outputs the ranking does not need (none changes the trained field or the judge's views)
FULL_RUN_SKIPS = ("stylize.video_frames=0", "export.enabled=false")
TARGET_S = 60.0


def run_cli(args: list[str], out_root: Path, what: str) -> tuple[dict[str, Any], float]:
    """Run ``python -m nerfart_plugin *args`` into ``out_root``: (its result.json, wall seconds)."""
    hydra_dir = out_root / "hydra" / f"{what}-{time.time_ns()}"
    cmd = [sys.executable, "-m", "nerfart_plugin", *args, f"output_root={out_root}", f"hydra.run.dir={hydra_dir}"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{what} failed:\n{(proc.stdout + proc.stderr)[-3000:]}")
    return json.loads((hydra_dir / "result.json").read_text()), seconds


def judge_gain(metrics: dict[str, Any]) -> float:
    judge = metrics["judge"]
    return judge["stylized"]["mean_target_prob"] - judge["source"]["mean_target_prob"]


def run_full(prompt: str, out_root: Path) -> dict[str, Any]:
    """The full stylization of ``prompt`` at this commit's defaults (reused when the root holds it)."""
    log.info("full run: %s", prompt)
    result, seconds = run_cli(["guidance=imagenet", f"+prompt={prompt}", *FULL_RUN_SKIPS], out_root, "full")
    folder = Path(result["stylization"]["dir"])
    metrics = json.loads((folder / "metrics.json").read_text())
    return {"prompt": prompt, "seconds": seconds, "folder": str(folder), "gain": judge_gain(metrics),
            "top5": metrics["judge"]["stylized"]["top5_rate"]}


def run_preview(prompt: str, out_root: Path, extra: list[str]) -> dict[str, Any]:
    log.info("preview: %s", prompt)
    result, seconds = run_cli(["stage=preview", "guidance=imagenet", f"+prompt={prompt}", *extra], out_root,
                              "preview")
    folder = Path(result["preview"]["preview"]).parent
    metrics = json.loads((folder / "metrics.json").read_text())
    return {"prompt": prompt, "seconds": seconds, "folder": str(folder), "gain": judge_gain(metrics),
            "top5": metrics["judge"]["stylized"]["top5_rate"], "fit_s": (metrics.get("stage_seconds") or {}).get("fit"),
            "silhouette_iou": metrics["silhouette_iou"], "steps": metrics["steps"],
            "resolution": metrics["resolution"], "strength": metrics.get("strength", 1.0), **guide_scores(metrics)}


def guide_scores(metrics: dict[str, Any]) -> dict[str, float]:
    """The guide's own readouts of a preview: its directional similarity (Eq. 4's direction, stylized - source
    image against target - source text) and its score gain (stylized minus source similarity to the prompt)."""
    return {"directional": metrics["clip_directional_similarity"],
            "guide_gain": metrics["clip_score"] - metrics["clip_score_source"]}


def works(top5: float) -> bool:
    """A full run works when the judge puts the target in its top 5 on at least 3 of its 4 held-out views."""
    return top5 >= 0.75 - 1e-9


def resemblance(preview: Path, full: Path, size: int = 128) -> Optional[dict[str, float]]:
    """How alike the preview's held-out views and the full run's are (SSIM at ``size`` px; the cosine of the
    judge's pooled last-block features), and the same for the source's views; None without the full run."""
    import imageio.v3 as iio
    import torch
    import torch.nn.functional as F
    from kornia.metrics import ssim

    from nerfart_plugin.guidance.imagenet import LitePerceptual

    def load(folder: Path, kind: str) -> dict[str, torch.Tensor]:
        return {f.name.split("_", 1)[1]: F.interpolate(torch.from_numpy(iio.imread(f)).permute(2, 0, 1).float()[None]
                                                        / 255, size=(size, size), mode="bilinear", antialias=True)
                for f in sorted((folder / "heldout").glob(f"{kind}_*.png"))}

    full_views = load(full, "stylized") if (full / "heldout").is_dir() else {}
    if not full_views:
        return None
    net = LitePerceptual(model="lite2", stages=(5,))
    pooled = lambda x: F.normalize(net.features(x)[0].mean((2, 3)), dim=-1)  # noqa: E731
    out = {}
    for name, views in (("preview", load(preview, "stylized")), ("source", load(full, "source"))):
        keys = [k for k in views if k in full_views]
        out[f"ssim_{name}"] = sum(float(ssim(views[k], full_views[k], 11).mean()) for k in keys) / len(keys)
        out[f"feature_{name}"] = sum(float((pooled(views[k]) * pooled(full_views[k])).sum()) for k in keys) / len(keys)
    return out


def fit_thresholds(scored: list[tuple[float, bool]]) -> tuple[float, float]:
    """Verdict thresholds (unlikely, likely) that make no error on ``scored`` ((directional, works) pairs):
    "likely" from halfway between the highest-scoring prompt that fails and the next one up, "unlikely" below
    halfway between the lowest-scoring prompt that works and the next one down; where no prompt fails (or none
    works) above (below) the others, the bound sits just past the extreme score."""
    scores = sorted(s for s, _ in scored)
    failing = [s for s, ok in scored if not ok]
    working = [s for s, ok in scored if ok]

    def between(edge: float, up: bool) -> float:
        beyond = [s for s in scores if (s > edge if up else s < edge)]
        return (edge + (min(beyond) if up else max(beyond))) / 2 if beyond else edge + (1e-3 if up else -1e-3)

    likely = between(max(failing), up=True) if failing else min(scores) - 1e-3
    unlikely = between(min(working), up=False) if working else max(scores) + 1e-3
    return min(unlikely, likely), likely


def leave_one_out(scored: list[tuple[str, float, bool]]) -> dict[str, Any]:
    """Each prompt's verdict from thresholds fitted on the others (:func:`fit_thresholds`): how the verdict does
    on a prompt it was not set on. Returns the tally ``{"right", "wrong", "uncertain", "wrong_prompts"}``."""
    tally: dict[str, Any] = {"right": 0, "wrong": 0, "uncertain": 0, "wrong_prompts": []}
    for i, (prompt, score, ok) in enumerate(scored):
        unlikely, likely = fit_thresholds([(s, w) for j, (_, s, w) in enumerate(scored) if j != i])
        if unlikely <= score < likely:
            tally["uncertain"] += 1
        elif (score >= likely) == ok:
            tally["right"] += 1
        else:
            tally["wrong"] += 1
            tally["wrong_prompts"].append(prompt)
    return tally


def rank_correlation(pairs: list[tuple[float, float]]) -> float:
    from scipy.stats import spearmanr

    return float(spearmanr(*zip(*pairs)).statistic) if len(pairs) >= 3 else float("nan")


def verdicts(previews: list[dict[str, Any]], full: dict[str, dict[str, Any]]) -> tuple[list[list[Any]], dict[str, Any]]:
    """Each preview's verdict (this commit's thresholds) against its full run: the table's rows and the tally."""
    from nerfart_plugin.run.stages.preview import verdict

    rows, tally = [], {"likely": [0, 0], "unlikely": [0, 0], "uncertain": 0, "wrong": []}
    for p in previews:
        f = full[p["prompt"]]
        word = verdict(p["directional"], "imagenet")["verdict"]
        ok = works(f["top5"])
        if word == "likely to work":
            tally["likely"][0 if ok else 1] += 1
        elif word == "unlikely to work":
            tally["unlikely"][0 if not ok else 1] += 1
        else:
            tally["uncertain"] += 1
        if (word == "likely to work" and not ok) or (word == "unlikely to work" and ok):
            tally["wrong"].append(p["prompt"])
        r = p.get("resemblance") or {}
        rows.append([p["prompt"], f"{p['directional']:.3f}", word, f"{100 * f['top5']:.0f}%", "yes" if ok else "no",
                     common.fmt(r.get("ssim_preview"), ".3f") + f" ({common.fmt(r.get('ssim_source'), '.3f')})",
                     common.fmt(r.get("feature_preview"), ".3f") + f" ({common.fmt(r.get('feature_source'), '.3f')})",
                     f"{p['silhouette_iou']:.3f}", f"{p['seconds']:.0f}"])
    return rows, tally


def report(raw: dict[str, Any], info: dict[str, Any], cmd: str) -> str:
    from nerfart_plugin.run.stages.preview import CALIBRATION

    full = {f["prompt"]: f for f in raw["full"]}
    previews = raw["previews"]
    rows, tally = verdicts(previews, full)
    scored = [(p["prompt"], p["directional"], works(full[p["prompt"]]["top5"])) for p in previews]
    fitted, loo = fit_thresholds([(sc, ok) for _, sc, ok in scored]), leave_one_out(scored)
    first = previews[0]
    cal = CALIBRATION["imagenet"]
    n_work = sum(works(full[p["prompt"]]["top5"]) for p in previews)
    body = [f"`stage=preview` ({' '.join(raw.get('override') or []) or 'defaults'}: {first['steps']} steps at "
            f"{first['resolution']} px with the full run's losses and views and the outline held, shown at strength "
            f"{first['strength']:g}) on the "
            "main-job benchmark's reconstruction of the head, `guidance=imagenet`, against the full stylization of "
            f"the same prompt at this commit's defaults. {n_work} of the {len(previews)} prompts work in the full run "
            "(the judge's top 5 on at least 3 of 4 held-out views). Resemblance to the full run's held-out views: "
            "SSIM at 128 px and the cosine of the judge's pooled features (Lite2, a network that guided neither), "
            "the source's own in brackets (what doing nothing scores); measured where the full run's folder is on "
            "this machine.", ""]
    body += common.md_table(["prompt", "guide directional", "verdict", "full-run top-5", "works",
                             "SSIM to the full run (source)", "features to the full run (source)",
                             "silhouette IoU with the source", "preview wall s"], rows)
    decided = sum(tally["likely"]) + sum(tally["unlikely"])
    right = tally["likely"][0] + tally["unlikely"][0]
    slow = max(p["seconds"] for p in previews)
    ious = [p["silhouette_iou"] for p in previews]
    resembling = [p["resemblance"] for p in previews if p.get("resemblance")]
    body += ["", f"**The verdict** (thresholds on the guide's directional similarity: likely >= {cal.likely:.3f}, "
             f"unlikely < {cal.unlikely:.3f}, uncertain between): {right} of the {decided} decided prompts right "
             f"(likely to work: {tally['likely'][0]} right, {tally['likely'][1]} wrong; unlikely: "
             f"{tally['unlikely'][0]} right, {tally['unlikely'][1]} wrong); {tally['uncertain']} uncertain"
             + (f"; wrong: {', '.join(tally['wrong'])}" if tally["wrong"] else "") + ". The thresholds were read off "
             "these same prompts, so this is the accuracy on the prompts they were set on; for scale, saying "
             f"\"likely\" of every prompt would be right on {n_work} of {len(previews)}.",
             "", f"**Thresholds fitted to these previews** (no error on them: likely from halfway between the "
             f"highest-scoring failure and the next score, unlikely below halfway between the lowest-scoring success "
             f"and the next): unlikely < {fitted[0]:.3f}, likely >= {fitted[1]:.3f}"
             + (" (this commit's)" if abs(fitted[0] - cal.unlikely) < 5e-4 and abs(fitted[1] - cal.likely) < 5e-4
                else " (this commit has other thresholds: set these in CALIBRATION to use them)") + ". "
             f"**Left out** (each prompt judged by thresholds fitted on the other {len(previews) - 1}, the accuracy on a "
             f"prompt the verdict was not set on): {loo['right']} right, {loo['wrong']} wrong, {loo['uncertain']} "
             "uncertain" + (f" (wrong: {', '.join(loo['wrong_prompts'])})" if loo["wrong_prompts"] else "") + ".",
             "", f"- the subject kept (silhouette IoU with the source >= 0.9): **{'MET' if min(ious) >= 0.9 else 'NOT MET'}** "
             f"({sum(i >= 0.9 for i in ious)} of {len(ious)}; below: "
             + (", ".join(f"{p['prompt']} {p['silhouette_iou']:.2f}" for p in previews if p["silhouette_iou"] < 0.9)
                or "none") + ")",
             f"- each preview <= {TARGET_S:.0f} s from the command's start: **{'MET' if slow <= TARGET_S else 'NOT MET'}** "
             f"(slowest {slow:.0f} s, median {sorted(p['seconds'] for p in previews)[len(previews) // 2]:.0f} s; "
             f"{sum(p['seconds'] <= TARGET_S for p in previews)} of {len(previews)} within)"]
    if resembling:
        by_ssim = sum(r["ssim_preview"] > r["ssim_source"] for r in resembling)
        by_features = sum(r["feature_preview"] > r["feature_source"] for r in resembling)
        body.append(f"- closer to the full run than the source is, of the {len(resembling)} prompts with a full run "
                    f"on this machine: in the judge's features {by_features}, in SSIM {by_ssim}")
    body += ["", *raw.get("notes", [])]
    return common.section(NAME, "The preview: does it look like the full run, and is its verdict right?", cmd, info,
                          body, False)


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """All previews first (their times are the target), then the full runs (``--keep-full``: the raw file's);
    each preview's resemblance to its full run where that run's folder is on this machine."""
    old = json.loads(Path(args.raw or common.raw_path(NAME, args.quick)).read_text()) if (args.add or args.keep_full) \
        else None
    known = {q["prompt"] for q in old["previews"]} if old is not None and args.add else set()
    prompts = [p for p in args.prompts if p not in known]
    previews = [run_preview(prompt, args.out_root, args.override) for prompt in prompts]
    if args.keep_full:
        full = [f for f in old["full"] if f["prompt"] in set(prompts)]
    else:
        full = [run_full(prompt, args.out_root) for prompt in prompts]
    by_prompt = {f["prompt"]: f for f in full}
    for p in previews:
        folder = _full_folder(p["prompt"], args.out_root) or Path(by_prompt[p["prompt"]]["folder"])
        p["resemblance"] = resemblance(Path(p["folder"]), folder)
    raw = {"previews": previews, "full": full, "override": args.override}
    if old is not None and args.add:
        raw = {**old, "previews": old["previews"] + raw["previews"], "full": old["full"] + raw["full"]}
    return raw


def _full_folder(prompt: str, root: Path) -> Optional[Path]:
    """The whole-scene stylization of ``prompt`` at the defaults in ``root`` (None when there is none)."""
    for metrics in sorted(Path(root).glob("stylizations/*/metrics.json")):
        m = json.loads(metrics.read_text())
        if m.get("prompt") == prompt and "region" not in m and m.get("guidance") == "imagenet":
            return metrics.parent
    return None


def retime(args: argparse.Namespace) -> dict[str, Any]:
    """Time the raw file's previews again, from scratch (each one's folder removed first), after a change that
    should only make them faster: the new wall and fit seconds replace the old ones, and each preview's scores
    must come out the same (the preview is seeded), else the run stops, since then it measured another preview."""
    import shutil

    raw = json.loads(Path(args.raw or common.raw_path(NAME, args.quick)).read_text())
    unknown = set(args.retime or ()) - {p["prompt"] for p in raw["previews"]}
    if unknown:
        raise SystemExit(f"--retime: no preview of {sorted(unknown)} in the raw file")
    for old in raw["previews"]:
        if args.retime and old["prompt"] not in args.retime:
            continue
        shutil.rmtree(old["folder"], ignore_errors=True)
        new = run_preview(old["prompt"], args.out_root, raw.get("override") or [])
        changed = {k: (old[k], new[k]) for k in ("gain", "top5", "directional", "guide_gain")
                   if abs(old[k] - new[k]) > 1e-6}
        if changed:
            raise SystemExit(f"the preview of {old['prompt']!r} changed on retiming: {changed}")
        old.update(seconds=new["seconds"], fit_s=new["fit_s"], folder=new["folder"])
    return raw


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--prompts", nargs="+", default=[*PROMPTS, *FRESH_PROMPTS])
    p.add_argument("--override", nargs="*", default=[], help="extra overrides, e.g. preview.steps=48")
    p.add_argument("--add", action="store_true", help="measure only the prompts the raw file lacks and append them")
    p.add_argument("--keep-full", action="store_true", help="run the previews, keep the raw file's full runs")
    p.add_argument("--retime", nargs="*", default=None, metavar="PROMPT", help="time the raw file's previews (or "
                   "only those of the prompts given) again from scratch (their scores must not change) and keep the "
                   "full runs")
    p.add_argument("--note", nargs="*", default=[], help="lines added to the report")
    p.add_argument("--out-root", type=Path, default=ROOT / "outputs" / "benchmarks" / "main_job",
                   help="the output root holding the cached reconstruction (the main-job benchmark's)")
    common.add_raw_args(p)
    common.add_common_args(p)
    args = p.parse_args(argv)
    info = common.start_logging(log)
    raw = common.raw_results(args, NAME, lambda: retime(args) if args.retime is not None else measure(args))
    raw["notes"] = args.note or raw.get("notes", [])
    common.finish(args, NAME, report(raw, info, common.command("preview.py", argv or sys.argv[1:])))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
