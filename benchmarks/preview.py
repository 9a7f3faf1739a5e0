"""Does the one-minute preview predict the full run?

For each prompt, ``python -m nerfart_plugin stage=preview guidance=imagenet +prompt=...`` runs on the
cached reconstruction in ``--out-root`` (the main-job benchmark's), timed from the command's start
(start-up, guide and judge loading included); then the full stylization of the same prompt runs at this
commit's defaults in the same root (``--full``; the run cache reuses a finished one; its video and
meshes are skipped, which changes no trained result). The preview's judge gain (mean target
probability on the held-out views, stylized minus source) is ranked against the full run's. The
default prompts mix styles that work on the head with objects that are expected to fail (a school bus,
a volcano), so the ranking covers failures too. Targets: Spearman >= 0.7 over >= 8 prompts, each
preview <= 60 s.

    python -m benchmarks preview --out-root /tmp/mj/out
    python -m benchmarks preview --prompts zebra tabby
    python -m benchmarks preview --out-root /tmp/mj/out --retime    # the same previews, timed again
    python -m benchmarks preview --out-root /tmp/mj/out --retime zebra     # only this one
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common

log = logging.getLogger("bench.preview")
NAME = "preview"
PROMPTS = ("brain coral", "jack-o'-lantern", "tabby", "honeycomb", "ski mask", "zebra", "goldfish",
           "jigsaw puzzle", "volcano", "school bus")
#: the prompts the guide's directional similarity was picked on as the predictor (of five tried on them: the
#: judge's gain, its log-ratio and log-rank, the guide's score gain and its directional similarity)
CHOSEN_ON = PROMPTS
#: prompts added afterwards to test that predictor on runs it was not picked on
FRESH_PROMPTS = ("strawberry", "snail", "teddy bear", "airliner", "pizza")
#: the full run's outputs the ranking does not need (none changes the trained field or the judge's views)
FULL_RUN_SKIPS = ("stylize.video_frames=0", "export.enabled=false")
TARGET_RHO, TARGET_S = 0.7, 60.0


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
            **guide_scores(metrics)}


def guide_scores(metrics: dict[str, Any]) -> dict[str, float]:
    """The guide's own readouts of a preview: its directional similarity (Eq. 4's direction, stylized - source
    image against target - source text) and its score gain (stylized minus source similarity to the prompt)."""
    return {"directional": metrics["clip_directional_similarity"],
            "guide_gain": metrics["clip_score"] - metrics["clip_score_source"]}


def succeeded(top5: float) -> bool:
    """A run counts as working when the judge puts the target in its top 5 on at least half the views."""
    return top5 >= 0.5


def rank_correlation(pairs: list[tuple[float, float]]) -> float:
    from scipy.stats import spearmanr

    return float(spearmanr(*zip(*pairs)).statistic) if len(pairs) >= 3 else float("nan")


def report(raw: dict[str, Any], info: dict[str, Any], cmd: str) -> str:
    full = {f["prompt"]: f for f in raw["full"]}
    previews = raw["previews"]
    has_guide = all("directional" in p for p in previews)
    rows, agree = [], 0
    for p in previews:
        f = full[p["prompt"]]
        agree += succeeded(p["top5"]) == succeeded(f["top5"])
        rows.append([p["prompt"] + ("" if p["prompt"] in CHOSEN_ON else " (fresh)"), f"{p['gain']:.4f}",
                     f"{100 * p['top5']:.0f}%", common.fmt(p.get("directional"), ".3f"), f"{f['gain']:.4f}",
                     f"{100 * f['top5']:.0f}%", f"{p['seconds']:.0f}", common.fmt(p["fit_s"], ".0f"),
                     f"{f['seconds']:.0f}"])
    rho = rank_correlation([(p["gain"], full[p["prompt"]]["gain"]) for p in previews])
    slow = max(p["seconds"] for p in previews)
    failing = sum(not succeeded(full[p["prompt"]]["top5"]) for p in previews)
    body = [f"`stage=preview` ({' '.join(raw.get('override') or []) or 'defaults'}) on the main-job benchmark's "
            "reconstruction of the head (this commit's defaults), `guidance=imagenet`, then the full stylization of "
            "the same prompt at the defaults in the same output root (its video and meshes skipped; a finished "
            "run is reused, so a full run's wall time may be that of the cache lookup). Judge gain: the mean "
            "target probability on the held-out views, stylized minus source; a run *works* when the target is "
            "in the judge's top 5 on at least half the views. Guide directional: the guide's own directional "
            "similarity on the preview's held-out views (Eq. 4's direction; what the log reports for any prompt).",
            ""]
    body += common.md_table(["prompt", "preview judge gain", "preview top-5", "preview guide directional",
                             "full-run judge gain", "full-run top-5", "preview wall s", "of it fitting s",
                             "full-run wall s"], rows)
    body += ["", "**Targets**", "",
             f"- rank correlation of the preview's judge gain with the full run's over {len(previews)} prompts "
             f"({failing} of them fail in the full run) >= {TARGET_RHO}: "
             f"**{'MET' if rho >= TARGET_RHO else 'NOT MET'}** (Spearman {rho:.2f})"]
    if has_guide:
        body += guide_verdicts(previews, full)
    body += [f"- the preview's judge says whether the full run works (top-5 on half the views or not) for {agree} "
             f"of {len(previews)} prompts",
             f"- each preview <= {TARGET_S:.0f} s from the command's start: "
             f"**{'MET' if slow <= TARGET_S else 'NOT MET'}** (slowest {slow:.0f} s)", "", *raw.get("notes", [])]
    return common.section(NAME, "The one-minute preview: does it predict the full run?", cmd, info, body, False)


def guide_verdicts(previews: list[dict[str, Any]], full: dict[str, dict[str, Any]]) -> list[str]:
    """The guide's directional similarity as the predictor: over all prompts, and over the fresh ones alone
    (it was picked on :data:`CHOSEN_ON`, so only the fresh prompts test it without that bias)."""
    pairs = [(p["directional"], full[p["prompt"]]["gain"]) for p in previews]
    fresh = [(p["directional"], full[p["prompt"]]["gain"]) for p in previews if p["prompt"] not in CHOSEN_ON]
    rho, rho_fresh = rank_correlation(pairs), rank_correlation(fresh)
    untested = "" if len(fresh) >= 3 else ", on the prompts it was picked on: not yet a test"
    lines = [f"- rank correlation of the preview's guide directional similarity with the full run's judge gain "
             f"over {len(pairs)} prompts >= {TARGET_RHO}: **{'MET' if rho >= TARGET_RHO else 'NOT MET'}{untested}** "
             f"(Spearman {rho:.2f}; this predictor was picked after the study of the first {len(CHOSEN_ON)} prompts)"]
    if len(fresh) >= 3:
        lines.append(f"- the same over the {len(fresh)} fresh prompts alone (not seen when it was picked): "
                     f"**{'MET' if rho_fresh >= TARGET_RHO else 'NOT MET'}** (Spearman {rho_fresh:.2f})")
    return lines


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """All previews first (their times are the target), then the full runs; with ``--add``, only the prompts
    the raw file lacks, appended to it."""
    old = json.loads(Path(args.raw or common.raw_path(NAME, args.quick)).read_text()) if args.add else None
    prompts = [p for p in args.prompts if old is None or p not in {q["prompt"] for q in old["previews"]}]
    previews = [run_preview(prompt, args.out_root, args.override) for prompt in prompts]
    raw = {"previews": previews, "full": [run_full(prompt, args.out_root) for prompt in prompts],
           "override": args.override}
    if old is not None:
        raw = {**old, "previews": old["previews"] + raw["previews"], "full": old["full"] + raw["full"]}
    return raw


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
    p.add_argument("--prompts", nargs="+", default=list(PROMPTS))
    p.add_argument("--override", nargs="*", default=[], help="extra overrides, e.g. preview.steps=48")
    p.add_argument("--add", action="store_true", help="measure only the prompts the raw file lacks and append them")
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
