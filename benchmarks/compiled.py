"""A compiled field: eager against compiled (``compile=on``), part by part, on the README's head.

Everything runs on the README job's reconstruction of the head (VolSDF on the TensorVM grid; trained into
``--root`` first when it is not there). Eager and compiled are measured in the same process, interleaved
(one eager call, one compiled call, repeated), so their ratio is what to read on a shared machine:

1. **field**: ``query`` on random points in the box, no grad colour-only (the viewer's and the stylization's
   no-grad pass), no grad with normals (4 finite-difference taps), and a training forward + backward;
2. **frame**: the web viewer's 256 px frame of the head (the viewer's own frame code), and where the compiled
   frame's time goes (the profiler's top operators);
3. **steps**: a reconstruction step (forward, backward, optimizer; two systems alternating step by step) and a
   stylization step (``guidance=imagenet``; blocks of steps alternating eager and compiled, each block's first
   step dropped), with the step's parts;
4. **compile time**: a fresh process compiling the field (no-grad and training graphs) with an empty kernel
   cache (cold), then another with the cache the first one filled (warm).

    python -m benchmarks compiled
    python -m benchmarks compiled --root /path/to/an/outputs/root/with/the/head   # reuse its reconstruction
    python -m benchmarks compiled --quick
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common

log = logging.getLogger("bench.compiled")
NAME = "compiled"
FRAME_SIDE = 256
PROMPT = "brain coral"
RECONSTRUCTION = ["stage=reconstruct"]
QUICK_RECONSTRUCTION = ["stage=reconstruct", "reconstruct.steps=40", "data.resolution=48", "export.enabled=false"]
FRAME_GOAL_S = 0.40


def interleaved(fns: dict[str, Callable[[], Any]], reps: int) -> dict[str, float]:
    """Median seconds of each of ``fns``, called in turn ``reps`` times (after one untimed call each)."""
    times: dict[str, list[float]] = {k: [] for k in fns}
    for f in fns.values():
        f()
    for _ in range(reps):
        for k, f in fns.items():
            t0 = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


# --------------------------------------------------------------------------- 1. the field
def field_parts(folder: Path, reps: int, n: int, device: str = "cpu") -> list[dict[str, Any]]:
    """Eager, fused lookups and compiled ``query`` of the run's field on ``n`` points: three uses (see the module
    docstring)."""
    import copy

    import torch

    from nerfart_plugin.api import open_run
    from nerfart_plugin.fields.compiled import evaluate, set_compiled, use_fused_kernels

    eager = open_run(folder, device=device).renderer.field
    comp, fused = copy.deepcopy(eager), copy.deepcopy(eager)
    set_compiled(comp)
    use_fused_kernels(fused)
    g = torch.Generator().manual_seed(0)
    x = ((torch.rand(n, 3, generator=g) * 2 - 1) * 0.8 * float(eager.bound)).to(device)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1).to(device)
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)

    def nograd(field: Any, normals: bool) -> Callable[[], Any]:
        def call() -> Any:
            with torch.no_grad():
                out = evaluate(field, x, d, with_normal=normals)
            sync()
            return out
        return call

    def train(field: Any) -> Callable[[], Any]:
        xs, ds = x[: n // 4], d[: n // 4]

        def call() -> None:
            field.train()
            out = evaluate(field, xs, ds, with_normal=True)
            loss = out["rgb"].square().mean() + sum(field.regularizers(out).values())
            field.zero_grad()
            loss.backward()
            sync()
        return call

    rows = []
    for label, make in ((f"no grad, colour only ({n} points)", lambda f: nograd(f, False)),
                        (f"no grad, with normals ({n} points)", lambda f: nograd(f, True)),
                        (f"training forward + backward ({n // 4} points)", train)):
        s = interleaved({"eager": make(eager), "fused": make(fused), "compiled": make(comp)}, reps)
        rows.append({"part": label, **s})
        log.info("field, %s: eager %.1f ms, fused lookups %.1f ms, compiled %.1f ms", label, 1e3 * s["eager"],
                 1e3 * s["fused"], 1e3 * s["compiled"])
    return rows


# --------------------------------------------------------------------------- 2. the viewer's frame
def frame(folder: Path, reps: int, side: int, device: str = "cpu") -> dict[str, Any]:
    """The viewer's ``side`` px frame (front camera), eager vs compiled, and the compiled frame's top operators."""
    import torch
    from torch.profiler import profile

    from nerfart_plugin.api import open_run
    from nerfart_plugin.fields.compiled import set_compiled, use_fused_kernels
    from nerfart_plugin.viewer.cameras import capture_camera
    from nerfart_plugin.viewer.sources import RunField, ViewSettings

    eager, comp = RunField(open_run(folder, device=device)), RunField(open_run(folder, device=device))
    fused = RunField(open_run(folder, device=device))
    set_compiled(comp.run.renderer)
    use_fused_kernels(fused.run.renderer)
    cam = capture_camera(eager.cameras, 0)
    t0 = time.perf_counter()
    comp.render(cam, side, ViewSettings())
    first = time.perf_counter() - t0
    s = interleaved({"eager": lambda: eager.render(cam, side, ViewSettings()),
                     "fused": lambda: fused.render(cam, side, ViewSettings()),
                     "compiled": lambda: comp.render(cam, side, ViewSettings())}, reps)
    diff = int(abs(eager.render(cam, side, ViewSettings()).astype(int)
                   - comp.render(cam, side, ViewSettings()).astype(int)).max())
    with torch.no_grad(), profile() as prof:
        comp.render(cam, side, ViewSettings())
    events = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
    total = sum(e.self_cpu_time_total for e in events) or 1.0
    top = [{"op": e.key, "share": e.self_cpu_time_total / total} for e in events[:8]]
    log.info("frame %d px: eager %.3f s, fused lookups %.3f s, compiled %.3f s (first compiled frame %.1f s)", side,
             s["eager"], s["fused"], s["compiled"], first)
    return {"side": side, **s, "first_compiled_s": first, "max_pixel_diff": diff, "top_ops": top}


# --------------------------------------------------------------------------- 3. training steps
def reconstruction_steps(overrides: list[str], steps: int) -> dict[str, Any]:  # on the overrides' device
    """A reconstruction step's parts (ms), eager, fused-lookup and compiled systems alternating step by step."""
    import lightning as L

    from benchmarks.step_split import timed_step
    from nerfart_plugin.fields.compiled import set_compiled, use_fused_kernels
    from nerfart_plugin.run.factories import build_reconstruction_system, build_scene
    from nerfart_plugin.systems.base import adam, param_groups

    scene = build_scene(common.compose(overrides))
    systems = {}
    for name in ("eager", "fused", "compiled"):
        L.seed_everything(0, verbose=False)
        system = build_reconstruction_system(scene)
        set_compiled(system, name == "compiled")
        use_fused_kernels(system, name != "eager")
        rc = scene.cfg.reconstruct
        systems[name] = (system, adam(param_groups(system.renderer, rc.lr, rc.lr_mlp)))
    parts: dict[str, dict[str, list[float]]] = {k: {"forward": [], "backward": [], "optimizer": []} for k in systems}
    for step in range(steps + 2):
        for name, (system, opt) in systems.items():
            seconds = timed_step(system, opt, step)
            if step >= 2:  # the compile happens in the first steps
                for k, v in seconds.items():
                    parts[name][k].append(1e3 * v)
    out = {name: {k: statistics.median(v) for k, v in p.items()} for name, p in parts.items()}
    for name in out:
        out[name]["step"] = sum(out[name].values())
    log.info("reconstruction step: %s", out)
    return out


def stylization_steps(checkpoint: Path, overrides: list[str], steps: int, blocks: int) -> dict[str, Any]:
    """A stylization step's parts (ms; :class:`~nerfart_plugin.systems.stylization.StylizationSystem`'s own
    timings), ``blocks`` blocks of ``steps`` steps each way, alternating eager, fused lookups and compiled."""
    from benchmarks.stylization import Context, run_steps

    ctx = Context(overrides, checkpoint)
    timings: dict[str, list[dict[str, float]]] = {"eager": [], "fused": [], "compiled": []}
    for _ in range(blocks):  # compile=auto on a few steps: uncompiled with the fused lookups
        for name, setting in (("eager", "compile=off"), ("fused", "compile=auto"), ("compiled", "compile=on")):
            # the block's length as the run's (all three alike), so that compile=auto decides as on a short run
            r = run_steps(ctx, [setting, f"stylize.steps={steps + 1}"], steps + 1, prompt=PROMPT)
            timings[name] += r["timings"][1:]  # the block's first step (the source cache, the compile) dropped
    out = {name: {k: 1e3 * statistics.median(t[k] for t in ts) for k in ts[0]} for name, ts in timings.items()}
    log.info("stylization step: %s", out)
    return out


# --------------------------------------------------------------------------- 4. compile time
COMPILE_PROBE = """
import sys, time, torch
from nerfart_plugin.api import open_run
from nerfart_plugin.fields.compiled import evaluate, set_compiled
field = open_run(sys.argv[1], device=sys.argv[2]).renderer.field
set_compiled(field)
x = torch.rand(4096, 3, device=sys.argv[2]) - 0.5
d = torch.nn.functional.normalize(torch.randn(4096, 3, device=sys.argv[2]), dim=-1)
t0 = time.perf_counter()
with torch.no_grad():
    evaluate(field, x, d, with_normal=False)
t1 = time.perf_counter()
field.train()
out = evaluate(field, x, d, with_normal=True)
(out["rgb"].sum() + sum(field.regularizers(out).values())).backward()
t2 = time.perf_counter()
print("COMPILE", t1 - t0, t2 - t1)
"""


def compile_times(folder: Path, device: str = "cpu") -> dict[str, Any]:
    """Seconds to compile the field's no-grad and training graphs in a fresh process: with an empty kernel
    cache (cold), then with the cache that run filled (warm)."""
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NERFART_COMPILE_CACHE": cache, "TORCHINDUCTOR_CACHE_DIR": cache}
        for label in ("cold", "warm"):
            proc = subprocess.run([sys.executable, "-c", COMPILE_PROBE, str(folder), device], cwd=ROOT, env=env,
                                  capture_output=True, text=True, check=True)
            line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("COMPILE"))
            nograd, train = map(float, line.split()[1:])
            out[label] = {"no_grad_s": nograd, "training_s": train}
            log.info("compile, %s cache: no grad %.1f s, training %.1f s", label, nograd, train)
    return out


# --------------------------------------------------------------------------- the main job
def main_job_rows(files: dict[str, Path]) -> list[dict[str, Any]]:
    """The first job of each ``python -m benchmarks main_job`` raw file (label -> file): its seconds, the two
    fits, the held-out PSNR, the judge's top-5 and what ``compile`` became in each stage."""
    rows = []
    for label, path in files.items():
        job = json.loads(Path(path).read_text())["jobs"][0]
        rec, sty = job["reconstruction"], job["stylization"]
        judge = sty.get("judge", {}).get("stylized", {})
        rows.append({"label": label, "seconds": job["seconds"], "reconstruction_fit": rec["stage_seconds"]["fit"],
                     "stylization_fit": sty["stage_seconds"]["fit"], "psnr": job["result"]["reconstruction"]["psnr"],
                     "top5": round(judge.get("top5_rate", 0) * len(judge.get("per_view", []))),
                     "views": len(judge.get("per_view", [])), "compile": [rec["auto"].get("compile", "–"),
                                                                          sty["auto"].get("compile", "–")]})
    return rows


# --------------------------------------------------------------------------- report
def main_job_lines(rows: list[dict[str, Any]]) -> list[str]:
    lines = ["", "**The main job** (`python -m benchmarks main_job --prompts 'brain coral'`, the README's job from an "
             "empty output root; the kernel cache emptied before the cold run, kept for the warm one):", ""]
    lines += common.md_table(
        ["run", "end to end (s)", "reconstruction fit (s)", "stylization fit (s)", "held-out PSNR (dB)", "judge top-5",
         "compile (reconstruction / stylization)"],
        [[r["label"], f"{r['seconds']:.0f}", f"{r['reconstruction_fit']:.0f}", f"{r['stylization_fit']:.0f}",
          f"{r['psnr']:.2f}", f"{r['top5']}/{r['views']}", " / ".join(r["compile"])] for r in rows])
    return lines


def report(raw: dict[str, Any], info: dict[str, Any], cmd: str, quick: bool) -> str:
    def ratio(e: float, c: Any) -> str:
        return f"{e / c:.2f}x" if c else "–"

    def ms(v: Any, digits: int = 1) -> str:
        return f"{v:.{digits}f}" if v is not None else "–"

    fr = raw["frame"]
    body = [f"Device: {raw.get('device', 'cpu')}. Three ways in one process, interleaved: **eager** (`compile=off`: "
            "PyTorch's kernels, the grid's lookups by `grid_sample`), **fused lookups** (the TensorVM grid's lookups "
            "in the package's fused CPU kernel, the rest eager: what `compile=auto` runs where the compile would not "
            "pay) and **compiled** (`compile=on`: each field's `query` through `torch.compile`, inductor, dynamic "
            "shapes, with the fused lookups inside the graph on a CPU, ATen's `grid_sample` on CUDA). Ratios are "
            "eager / the other (above 1: faster than eager).", "",
            "**The field** (the head's VolSDF on the TensorVM grid, random points in the box):", ""]
    body += common.md_table(
        ["use", "eager (ms)", "fused lookups (ms)", "compiled (ms)", "ratio fused", "ratio compiled"],
        [[r["part"], ms(1e3 * r["eager"]), ms(1e3 * r["fused"]) if "fused" in r else "–", ms(1e3 * r["compiled"]),
          ratio(r["eager"], r.get("fused")), ratio(r["eager"], r["compiled"])] for r in raw["field"]])
    met = "met" if fr["compiled"] <= FRAME_GOAL_S else "NOT met"
    fused_frame = f"fused lookups {fr['fused']:.3f} s ({ratio(fr['eager'], fr['fused'])}), " if "fused" in fr else ""
    body += ["", f"**The viewer's {fr['side']} px frame** of the head: eager {fr['eager']:.3f} s, {fused_frame}compiled "
             f"{fr['compiled']:.3f} s ({ratio(fr['eager'], fr['compiled'])}; goal <= {FRAME_GOAL_S} s: {met}); the "
             f"first compiled frame {fr['first_compiled_s']:.1f} s (the compile); largest pixel difference "
             f"{fr['max_pixel_diff']} of 255. Where the compiled frame's time goes (the profiler's self time):", ""]
    body += common.md_table(["operator", "share"], [[f"`{t['op']}`", f"{100 * t['share']:.1f}%"]
                                                   for t in fr["top_ops"]])
    rs, ss = raw["reconstruction"], raw["stylization"]
    body += ["", "**Training steps** (median ms; the stylization step's parts are the system's own timings):", ""]

    def step_row(stage: str, part: str, t: dict[str, Any], digits: int) -> list[str]:
        f = t.get("fused", {}).get(part)
        return [f"{stage}: {part}", ms(t["eager"][part], digits), ms(f, digits), ms(t["compiled"][part], digits),
                ratio(t["eager"][part], f), ratio(t["eager"][part], t["compiled"][part])]

    rows = [step_row("reconstruction", k, rs, 1) for k in ("forward", "backward", "optimizer", "step")]
    rows += [step_row("stylization", k, ss, 0) for k in ss.get("eager", {})]
    if "error" in ss:
        rows.append(["stylization: not measured", ss["error"][:120], "", "", "", ""])
    body += common.md_table(["step part", "eager", "fused lookups", "compiled", "ratio fused", "ratio compiled"],
                            rows)
    ct = raw["compile"]
    body += ["", f"**Compile time** of the field (a fresh process; no-grad graph + training graph): empty kernel "
             f"cache {ct['cold']['no_grad_s']:.1f} + {ct['cold']['training_s']:.1f} s, warm cache "
             f"{ct['warm']['no_grad_s']:.1f} + {ct['warm']['training_s']:.1f} s."]
    if raw.get("main_job"):
        body += main_job_lines(raw["main_job"])
    for note in raw.get("notes", []):
        body += ["", note]
    return common.section(NAME, "A compiled field", cmd, info, body, quick)


def measure(args: argparse.Namespace) -> dict[str, Any]:
    q = args.quick
    recon = QUICK_RECONSTRUCTION if q else RECONSTRUCTION
    dev = [f"device={args.device}"]
    folder = common.trained_run(args.root, [*recon, *dev])
    reps = 2 if q else args.reps
    raw: dict[str, Any] = {"run": str(folder), "device": args.device}
    raw["field"] = field_parts(folder, reps, 4096 if q else 65536, args.device)
    raw["frame"] = frame(folder, reps, 32 if q else FRAME_SIDE, args.device)
    raw["reconstruction"] = reconstruction_steps([f"output_root={args.root}", *recon, *dev], 3 if q else args.steps)
    style = [*dev, "guidance=toy"] if q else [*dev, "guidance=imagenet"]
    try:
        raw["stylization"] = stylization_steps(folder / "final.ckpt", [*recon[1:], *style, "stylize.resolution=32"]
                                               if q else style, 2 if q else 6, 1 if q else 2)
    except Exception as exc:  # noqa: BLE001 - e.g. the guide's weights missing on a GPU machine: say so, go on
        raw["stylization"] = {"error": f"{type(exc).__name__}: {exc}"}
        log.warning("stylization steps not measured: %s", raw["stylization"]["error"])
    raw["compile"] = compile_times(folder, args.device)
    return raw


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--root", type=Path, default=ROOT / "outputs" / "benchmarks" / "compiled",
                   help="outputs root holding (or to hold) the head's reconstruction")
    p.add_argument("--reps", type=int, default=9, help="interleaved repetitions of the field and frame timings")
    p.add_argument("--steps", type=int, default=20, help="reconstruction steps timed each way")
    p.add_argument("--device", default="cpu", help="cpu | cuda (the GPU check runs it on cuda)")
    common.add_common_args(p)
    p.add_argument("--main-jobs", nargs="*", default=[], metavar="LABEL=FILE",
                   help="raw files of `python -m benchmarks main_job` runs to tabulate (e.g. cold=a.json)")
    p.add_argument("--note", nargs="*", default=[], help="lines added to the report")
    p.add_argument("--notes-file", type=Path, help="a Markdown file whose paragraphs are added to the report "
                   "(after --note's lines)")
    common.add_raw_args(p)
    args = p.parse_args(argv)
    info = common.start_logging(log)
    raw = common.raw_results(args, NAME, lambda: measure(args))
    if args.main_jobs:
        raw["main_job"] = main_job_rows(dict(a.split("=", 1) for a in args.main_jobs))
    notes = list(args.note)
    if args.notes_file:
        notes += [par.strip() for par in args.notes_file.read_text().split("\n\n") if par.strip()]
    if notes:
        raw["notes"] = notes
    if args.main_jobs or notes:
        Path(args.raw or common.raw_path(NAME, args.quick)).write_text(json.dumps(raw, indent=1, default=str))
    common.finish(args, NAME, report(raw, info, common.command(NAME, argv), args.quick))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
