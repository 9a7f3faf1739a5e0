"""Does the one-minute preview predict the full run?

For each prompt, ``python -m nerfart_plugin stage=preview guidance=imagenet +prompt=...`` runs on the
cached reconstruction of the main-job benchmark (``benchmarks/main_job.py``'s output root), timed
from the command's start (start-up, guide and judge loading included). Its judge gain (mean target
probability on the held-out views, preview minus source) is ranked against the full run's, read from
the full runs of the same settings: the main-job benchmark's (``benchmarks/results/main_job.json``)
and the stylization-quality benchmark's head runs (``benchmarks/results/stylization_quality.json``,
config ``full``). Targets: Spearman >= 0.7 over the prompts, each preview <= 60 s.

    python benchmarks/preview.py
    python benchmarks/preview.py --prompts zebra tabby
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
sys.path.insert(0, str(ROOT))

from benchmarks import common  # noqa: E402

log = logging.getLogger("bench.preview")
NAME = "preview"
PROMPTS = ("brain coral", "jack-o'-lantern", "tabby", "honeycomb", "ski mask")
TARGET_RHO, TARGET_S = 0.7, 60.0


def full_run_gains() -> dict[str, float]:
    """prompt -> the full run's judge gain (stylized minus source mean target probability)."""
    gains: dict[str, float] = {}
    quality = common.RAW_DIR / "stylization_quality.json"
    if quality.is_file():
        for r in json.loads(quality.read_text()):
            if r.get("scene") == "head" and r.get("config") == "full" and r.get("patches") is None:
                gains[r["prompt"]] = r["judge_p"] - r["judge_p_source"]
    main = common.RAW_DIR / "main_job.json"
    if main.is_file():  # the fresher runs, at this commit's defaults
        for job in json.loads(main.read_text())["jobs"]:
            judge = job["stylization"]["judge"]
            gains[job["prompt"]] = judge["stylized"]["mean_target_prob"] - judge["source"]["mean_target_prob"]
    return gains


def run_preview(prompt: str, out_root: Path, extra: list[str]) -> dict[str, Any]:
    hydra_dir = out_root / "hydra" / f"preview-{time.time_ns()}"
    args = [sys.executable, "-m", "nerfart_plugin", "stage=preview", "guidance=imagenet", f"+prompt={prompt}",
            f"output_root={out_root}", f"hydra.run.dir={hydra_dir}", *extra]
    t0 = time.perf_counter()
    proc = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"preview of {prompt!r} failed:\n{(proc.stdout + proc.stderr)[-3000:]}")
    folder = Path(json.loads((hydra_dir / "result.json").read_text())["preview"]["preview"]).parent
    metrics = json.loads((folder / "metrics.json").read_text())
    judge = metrics["judge"]
    return {"prompt": prompt, "seconds": seconds, "folder": str(folder),
            "gain": judge["stylized"]["mean_target_prob"] - judge["source"]["mean_target_prob"],
            "top5": judge["stylized"]["top5_rate"], "fit_s": (metrics.get("stage_seconds") or {}).get("fit")}


def report(raw: dict[str, Any], info: dict[str, Any], cmd: str) -> str:
    from scipy.stats import spearmanr

    full = raw["full"]
    rows = [[p["prompt"], f"{p['gain']:.4f}", f"{100 * p['top5']:.0f}%", common.fmt(full.get(p["prompt"]), ".3f"),
             f"{p['seconds']:.0f}", common.fmt(p["fit_s"], ".0f")] for p in raw["previews"]]
    paired = [(p["gain"], full[p["prompt"]]) for p in raw["previews"] if p["prompt"] in full]
    rho = float(spearmanr(*zip(*paired)).statistic) if len(paired) >= 3 else float("nan")
    slow = max(p["seconds"] for p in raw["previews"])
    body = [f"`stage=preview` ({' '.join(raw.get('override') or []) or 'defaults'}) on the main-job benchmark's "
            "reconstruction of the head, `guidance=imagenet`; full-run gains from the main-job and "
            "stylization-quality benchmarks (same defaults, 256 px, 200 steps).", ""]
    body += common.md_table(["prompt", "preview judge gain", "preview top-5", "full-run judge gain",
                             "preview wall s", "of it fitting s"], rows)
    body += ["", "**Targets**", "",
             f"- rank correlation of the preview's judge gain with the full run's over {len(paired)} prompts "
             f">= {TARGET_RHO}: **{'MET' if rho >= TARGET_RHO else 'NOT MET'}** (Spearman {rho:.2f}); the issue "
             "asks for >= 8 prompts including some that fail: only prompts with a full run at these defaults "
             "can be ranked, and these all succeed in the full run",
             f"- each preview <= {TARGET_S:.0f} s from the command's start: "
             f"**{'MET' if slow <= TARGET_S else 'NOT MET'}** (slowest {slow:.0f} s)", "", *raw.get("notes", [])]
    return common.section(NAME, "The one-minute preview: does it predict the full run?", cmd, info, body, False)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--prompts", nargs="+", default=list(PROMPTS))
    p.add_argument("--override", nargs="*", default=[], help="extra overrides, e.g. preview.steps=48")
    p.add_argument("--note", nargs="*", default=[], help="lines added to the report")
    p.add_argument("--out-root", type=Path, default=ROOT / "outputs" / "benchmarks" / "main_job",
                   help="the output root holding the cached reconstruction (the main-job benchmark's)")
    common.add_raw_args(p)
    common.add_common_args(p)
    args = p.parse_args(argv)
    info = common.start_logging(log)
    raw = common.raw_results(args, NAME, lambda: {"previews": [run_preview(prompt, args.out_root, args.override)
                                                               for prompt in args.prompts], "full": full_run_gains(),
                                                  "override": args.override})
    raw["notes"] = args.note or raw.get("notes", [])
    common.finish(args, NAME, report(raw, info, common.command("preview.py", argv or sys.argv[1:])))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
