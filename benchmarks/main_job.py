"""The README's main job, timed stage by stage from a clean output root, with its quality.

The job is the quick start's command, run as a user runs it (a subprocess of
``python -m nerfart_plugin``), into an output root emptied first:

    python -m nerfart_plugin guidance=imagenet +prompt="brain coral"

then the same command for each further prompt (the cached reconstruction is reused, as a user's
second prompt reuses it). Each stage records where its time went in its ``metrics.json``
(``stage_seconds``: fit, evaluation, video, meshes); the rest of the wall time (start-up, data,
guide and judge loading) is reported as "start-up and loading". Quality, from the same files:
the reconstruction's held-out PSNR (all held-out views) and, per prompt, the judge's top-5 hits on
the held-out views (:mod:`benchmarks.stylization_quality` explains the judge).

Targets (issue "fast feedback"): the first job <= 12 min end to end; held-out PSNR >= 27.5 dB;
the judge's top-5 on >= 3 of the 4 held-out views for every prompt; no stage repeats work an
earlier one wrote (the stylization copies the reconstruction's source mesh and texture).

    python -m benchmarks main_job                      # the README job + 2 more prompts
    python -m benchmarks main_job --prompts "brain coral"
    python -m benchmarks main_job --quick              # smoke run (tiny schedule, not a result)
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Optional, Sequence

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common

log = logging.getLogger("bench.main_job")
NAME = "main_job"
PROMPTS = ("brain coral", "jack-o'-lantern", "tabby")
README_ARGS = ["guidance=imagenet"]
QUICK_ARGS = ["reconstruct.steps=30", "stylize.steps=2", "data.resolution=48", "stylize.video_frames=2",
              "export.resolution=32", "export.texture_size=64"]
TARGET_S, TARGET_PSNR, TARGET_VIEWS = 720.0, 27.5, 3
STAGE_PARTS = ("fit", "evaluation", "video", "meshes")


def run_job(prompt: str, out_root: Path, extra: Sequence[str]) -> dict[str, Any]:
    """One ``python -m nerfart_plugin`` job; its wall seconds, exit code and the log's tail."""
    hydra_dir = out_root / "hydra" / f"{len(list((out_root / 'hydra').glob('*'))) if (out_root / 'hydra').exists() else 0}"
    args = [sys.executable, "-m", "nerfart_plugin", *README_ARGS, f"+prompt={prompt}", f"output_root={out_root}",
            f"hydra.run.dir={hydra_dir}", *extra]
    log.info("running: %s", " ".join(args[1:]))
    t0 = time.perf_counter()
    proc = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, check=False,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"})
    seconds = time.perf_counter() - t0
    text = proc.stdout + proc.stderr
    if proc.returncode != 0:
        raise SystemExit(f"the job for {prompt!r} failed (exit {proc.returncode}):\n{text[-4000:]}")
    result = json.loads((hydra_dir / "result.json").read_text())
    return {"prompt": prompt, "seconds": seconds, "result": result,
            "source_mesh_copied": "source mesh: copied from" in text}


def read_metrics(folder: Optional[str]) -> dict[str, Any]:
    return json.loads((Path(folder) / "metrics.json").read_text()) if folder else {}


def measure(prompts: Sequence[str], out_root: Path, extra: Sequence[str]) -> dict[str, Any]:
    if out_root.exists():
        shutil.rmtree(out_root)
    out_root.mkdir(parents=True)
    jobs = []
    for prompt in prompts:
        job = run_job(prompt, out_root, extra)
        res = job["result"]
        job["reconstruction"] = read_metrics((res.get("reconstruction") or {}).get("dir"))
        job["stylization"] = read_metrics(res["stylization"]["dir"])
        jobs.append(job)
        log.info("%s: %.0f s", prompt, job["seconds"])
    return {"jobs": jobs}


# --------------------------------------------------------------------------- report
def stage_rows(job: dict[str, Any]) -> list[list[str]]:
    rows, total_parts = [], 0.0
    for stage in ("reconstruction", "stylization"):
        parts = job[stage].get("stage_seconds") or {}
        for part in STAGE_PARTS:
            if part in parts:
                rows.append([f"{stage}: {part}", common.fmt(parts[part], ".0f")])
                total_parts += parts[part]
    rows.append(["start-up and loading (the rest)", common.fmt(job["seconds"] - total_parts, ".0f")])
    rows.append(["**end to end**", f"**{job['seconds']:.0f}** ({job['seconds'] / 60:.1f} min)"])
    return rows


def judge_views(metrics: dict[str, Any]) -> tuple[int, int]:
    per_view = ((metrics.get("judge") or {}).get("stylized") or {}).get("per_view") or []
    return sum(1 for v in per_view if v.get("target_rank", 99) < 5), len(per_view)


def quality_rows(jobs: list[dict[str, Any]]) -> list[list[str]]:
    rows = []
    for job in jobs:
        m = job["stylization"]
        hits, n = judge_views(m)
        judge = m.get("judge") or {}
        rows.append([job["prompt"], f"{hits}/{n}",
                     f"{common.fmt((judge.get('source') or {}).get('mean_target_prob'), '.4f')} → "
                     f"{common.fmt((judge.get('stylized') or {}).get('mean_target_prob'), '.3f')}",
                     common.fmt(job["seconds"], ".0f"), "yes" if job["source_mesh_copied"] else "NO"])
    return rows


def verdicts(jobs: list[dict[str, Any]]) -> list[str]:
    first = jobs[0]
    psnr = first["reconstruction"].get("psnr")
    lines = [f"- end to end <= {TARGET_S / 60:.0f} min: **{'MET' if first['seconds'] <= TARGET_S else 'NOT MET'}** "
             f"({first['seconds'] / 60:.1f} min)",
             f"- held-out PSNR >= {TARGET_PSNR} dB: **{'MET' if psnr is not None and psnr >= TARGET_PSNR else 'NOT MET'}** "
             f"({common.fmt(psnr)} dB over all held-out views)"]
    ok = all(judge_views(j["stylization"])[0] >= TARGET_VIEWS for j in jobs)
    lines.append(f"- judge top-5 on >= {TARGET_VIEWS} of 4 held-out views for every prompt: "
                 f"**{'MET' if ok else 'NOT MET'}**")
    copied = all(j["source_mesh_copied"] for j in jobs)
    lines.append(f"- the stylization copies the reconstruction's source mesh and texture instead of extracting and "
                 f"baking them again: **{'MET' if copied else 'NOT MET'}**")
    return lines


def report(raw: dict[str, Any], info: dict[str, Any], cmd: str, quick: bool) -> str:
    jobs = raw["jobs"]
    first = jobs[0]
    recon = first["reconstruction"]
    body = [f"The README's main job (`python -m nerfart_plugin guidance=imagenet +prompt=\"{first['prompt']}\"`) from "
            "an empty output root, then the same command with the other prompts (reusing the reconstruction). "
            f"Defaults of this commit{' plus ' + ' '.join(raw['extra']) if raw.get('extra') else ''}: reconstruction "
            f"{recon.get('steps')} steps, stylization {first['stylization'].get('steps')} steps. Stage times from each "
            "run's `metrics.json` (`stage_seconds`); the rest of the wall time is start-up, data, guide and judge "
            "loading.", "", f"### The first job, stage by stage ({first['prompt']})", ""]
    body += common.md_table(["stage", "seconds"], stage_rows(first))
    body += ["", "### Quality per prompt", ""]
    body += common.md_table(["prompt", "judge top-5 (held-out views)", "judge P(target) source → stylized",
                             "job seconds", "source mesh copied"], quality_rows(jobs))
    body += ["", f"Reconstruction: held-out PSNR {common.fmt(recon.get('psnr'))} dB, SSIM "
                 f"{common.fmt(recon.get('ssim'), '.3f')} (all held-out views).", "", "**Targets**", ""]
    body += verdicts(jobs)
    body += ["", *raw.get("notes", [])]
    return common.section(NAME, "The main job end to end (README quick start)", cmd, info, body, quick)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--prompts", nargs="+", default=list(PROMPTS), help="the first is the README's job")
    p.add_argument("--out-root", type=Path, default=ROOT / "outputs" / "benchmarks" / "main_job",
                   help="output root of the jobs (emptied first)")
    p.add_argument("--override", nargs="*", default=[], help="extra overrides for every job")
    common.add_raw_args(p)
    p.add_argument("--first-from", type=Path, default=None,
                   help="with --report-only: take the first (timed) job from this raw file, e.g. a re-run of the "
                        "README job alone on a quiet machine, and the other prompts from --raw")
    p.add_argument("--note", nargs="*", default=[], help="lines added to the report")
    common.add_common_args(p)
    args = p.parse_args(argv)
    info = common.start_logging(log)
    extra = [*(QUICK_ARGS if args.quick else []), *args.override]
    raw = common.raw_results(args, NAME, lambda: {**measure(args.prompts[:1] if args.quick else args.prompts,
                                                            args.out_root, extra), "extra": extra})
    if args.first_from:
        raw["jobs"][0] = json.loads(args.first_from.read_text())["jobs"][0]
    raw["notes"] = args.note or raw.get("notes", [])
    common.finish(args, NAME, report(raw, info, common.command("main_job.py", argv or sys.argv[1:]), args.quick))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
