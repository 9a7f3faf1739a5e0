"""Where a reconstruction step's time goes: forward, backward and optimizer, versus the grid side.

A bigger grid encoding resolves more of the images (``encoding.resolution=auto`` gives fern
``images_8`` side 256, where 128 left a cell about 6 px wide), but every step then pays for the
whole grid twice: the dense gradient that ``grid_sample``'s backward writes, and the optimizer's
pass over every cell. This benchmark times the three parts of a training step of the fern scene
(NeRF, ``render.num_samples=16``, weighted sampling: the forward-facing default) at several grid
sides, with both stages' optimizer (``systems.base.adam``: torch's fused Adam) and with the plain
(per-tensor loop) Adam it replaces; all figures of one run come from the same process, so their
ratios are what to read on a noisy machine.

    python -m benchmarks step_split
    python -m benchmarks step_split --sides 128 256 384 --steps 60
    python -m benchmarks step_split --quick
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

log = logging.getLogger("bench.step_split")
NAME = "step_split"
SCENE = ["data=llff", "data.path={shared}/llff_fern", "data.factor=8", "backbone=nerf", "render.num_samples=16"]
QUICK = ["data.resolution=48"]


def time_steps(system: Any, optimizer: Any, steps: int, warmup: int) -> dict[str, float]:
    """Median milliseconds of forward (render + loss), backward and optimizer step over ``steps`` steps
    (after ``warmup`` untimed ones) of ``system``'s own ray draws and losses."""
    parts: dict[str, list[float]] = {"forward": [], "backward": [], "optimizer": []}
    for step in range(warmup + steps):
        seconds = timed_step(system, optimizer, step)
        if step >= warmup:
            for k in parts:
                parts[k].append(1e3 * seconds[k])
    return {k: statistics.median(v) for k, v in parts.items()}


def timed_step(system: Any, optimizer: Any, step: int) -> dict[str, float]:
    """One reconstruction step of ``system`` (its own ray draw, seeded by ``step``, and losses): the seconds of
    its forward (render + loss), backward and optimizer step."""
    import torch

    from nerfart_plugin.systems.loss_terms import weighted_sum

    torch.manual_seed(step)
    batch = system.sample_batch(step)
    t0 = time.perf_counter()
    out = system.renderer(batch, perturb=True)
    terms, weights = system.losses(out, batch)
    loss = weighted_sum(terms, weights, step, "reconstruct")
    t1 = time.perf_counter()
    optimizer.zero_grad()
    loss.backward()
    t2 = time.perf_counter()
    optimizer.step()
    t3 = time.perf_counter()
    return {"forward": t1 - t0, "backward": t2 - t1, "optimizer": t3 - t2}


def measure(sides: list[int], steps: int, warmup: int, extra: list[str]) -> list[dict[str, Any]]:
    """One row per (grid side, optimizer): the step's parts in ms and the grid's parameter count."""
    import lightning as L
    import torch

    from nerfart_plugin.run.factories import build_reconstruction_system, build_scene
    from nerfart_plugin.systems.base import adam, param_groups

    shared = common.shared_data()
    base = [o.format(shared=shared) for o in SCENE] + extra
    scene = build_scene(common.compose(["stage=reconstruct", *base]))
    rows = []
    for side in sides:
        ctx = scene.with_config(common.compose(["stage=reconstruct", *base, f"encoding.resolution={side}"]))
        for name in ("fused (adam)", "plain"):
            L.seed_everything(0, verbose=False)
            system = build_reconstruction_system(ctx)
            groups = param_groups(system.renderer, ctx.cfg.reconstruct.lr, ctx.cfg.reconstruct.lr_mlp)
            opt = adam(groups) if name.startswith("fused") else torch.optim.Adam(groups, betas=(0.9, 0.99),
                                                                                 eps=1e-15, foreach=False)
            ms = time_steps(system, opt, steps, warmup)
            n_grid = sum(p.numel() for p in system.renderer.field.grid_parameters())
            rows.append({"side": side, "variant": name, "grid_params": n_grid, **ms,
                         "step": sum(ms.values())})
            log.info("side %d %s: %s", side, name, ", ".join(f"{k} {v:.1f} ms" for k, v in ms.items()))
    return rows


def report(rows: list[dict[str, Any]], info: dict, cmd: str, quick: bool, steps: int) -> str:
    body = [f"One fern training step (NeRF, 512 rays, 16 weighted samples per ray), median of {steps} steps after "
            "a warm-up, in ms; `fused (adam)` is what both stages use (`systems/base.py: adam`), `plain` the "
            "per-tensor loop Adam (`foreach=False`).", ""]
    table = [[r["side"], r["variant"], f"{r['grid_params'] / 1e6:.2f} M", common.fmt(r["forward"], ".1f"),
              common.fmt(r["backward"], ".1f"), common.fmt(r["optimizer"], ".1f"), common.fmt(r["step"], ".1f")]
             for r in rows]
    body += common.md_table(["grid side", "optimizer", "grid parameters", "forward (ms)", "backward (ms)",
                             "optimizer (ms)", "step (ms)"], table, "llrrrrr")
    by = {(r["side"], r["variant"].split()[0]): r for r in rows}
    ratios = [f"side {s}: optimizer {by[(s, 'plain')]['optimizer'] / max(by[(s, 'fused')]['optimizer'], 1e-9):.1f}x "
              f"faster fused, step {by[(s, 'plain')]['step'] / max(by[(s, 'fused')]['step'], 1e-9):.2f}x"
              for s in sorted({r["side"] for r in rows}) if (s, "plain") in by and (s, "fused") in by]
    if ratios:
        body += ["", "Fused versus plain, same run: " + "; ".join(ratios) + "."]
    return common.section(NAME, "Reconstruction step: forward, backward and optimizer versus the grid side", cmd,
                          info, body, quick)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sides", type=int, nargs="+", default=[128, 256, 384])
    p.add_argument("--steps", type=int, default=60, help="timed steps per configuration (median)")
    p.add_argument("--override", nargs="*", default=[], help="extra Hydra overrides")
    common.add_common_args(p)
    args = p.parse_args(argv)
    info = common.start_logging(log)
    steps, warmup = (3, 1) if args.quick else (args.steps, 10)
    sides = [16, 32] if args.quick else args.sides
    rows = measure(sides, steps, warmup, [*(QUICK if args.quick else []), *args.override])
    common.finish(args, NAME, report(rows, info, common.command("step_split.py", argv), args.quick, steps))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
