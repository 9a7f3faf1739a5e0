"""Accuracy/speed benchmark of the marching-cubes MeshExtractor on analytic SDFs.

For a sphere (r=0.5) and a torus (R=0.5, r=0.2) inside [-1,1]^3, extract meshes at
several grid resolutions and measure the Chamfer distance to the TRUE surface
(``tests/analytic_fields.py``'s ``chamfer_to_analytic``: |sdf| at samples on the
mesh, and distance from samples of the analytic surface to the mesh; L1
convention, world units), extraction time (grid evaluation + marching cubes +
floater pass, no colour) and vertex count.

Writes its table into BENCHMARKS.md between ``<!-- mesh_extraction:start -->``
and ``<!-- mesh_extraction:end -->`` (other sections are preserved).

    python -m benchmarks mesh_extraction                        # 32 64 128 256
    python -m benchmarks mesh_extraction --resolutions 32 64 128 256 512
"""

from __future__ import annotations

import argparse
import itertools
import logging
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

from benchmarks import common
from nerfart_plugin.export.compare import chamfer_to_analytic
from nerfart_plugin.export.mesh import MeshExtractor
from nerfart_plugin.fields.analytic import SphereSDF, TorusSDF

log = logging.getLogger("mesh_extraction")
NAME = "mesh_extraction"
START, END = common.markers(NAME)


def run(resolutions: list[int], n_samples: int) -> list[dict]:
    shapes = {"sphere r=0.5": SphereSDF(0.5), "torus R=0.5 r=0.2": TorusSDF(0.5, 0.2)}
    rows = []
    for name, field in shapes.items():
        for res in resolutions:
            ex = MeshExtractor(resolution=res, bound=1.0, color=False, show_progress=False)
            t0 = time.perf_counter()
            mesh = ex.extract(field)
            secs = time.perf_counter() - t0
            acc = chamfer_to_analytic(mesh, field, n_samples=n_samples)
            row = {
                "shape": name,
                "res": res,
                "cell": 2.0 / (res - 1),
                "seconds": secs,
                "vertices": len(mesh.vertices),
                "faces": len(mesh.faces),
                "watertight": mesh.is_watertight,
                **acc,
            }
            rows.append(row)
            log.info("%s res %d: chamfer %.3e (%.2f s)", name, res, acc["chamfer"], secs)
    return rows


def table(rows: list[dict], argv: list[str], n_samples: int, info: dict) -> str:
    cmd = " ".join(["python -m benchmarks mesh_extraction", *argv])
    lines = [
        START,
        "## Mesh extraction accuracy (marching cubes on analytic SDFs)",
        "",
        f"Command (from the repo root): `{cmd}`  ",
        common.machine_line(info),
        "",
        (
            f"Grid over [-1,1]^3, cell = 2/(res-1). Distances in world units, {n_samples} samples per direction. "
            "mesh→surface = mean |sdf| at samples on the extracted mesh; surface→mesh = mean distance from samples "
            "of the true surface to the mesh; Chamfer = mean of the two (L1 convention); Hausdorff = max of both. "
            "Time = grid evaluation + marching cubes (no colour). Chamfer falls ~4x per resolution doubling "
            "(second order in the cell size); Hausdorff stops falling at high resolution because it is set by a few "
            "isolated marching-cubes deviations (~cell/50) where the surface crosses grid planes."
        ),
        "",
        "| shape | res | cell | vertices | watertight | time (s) | mesh→surface | surface→mesh | Chamfer | Hausdorff |",
        "|---|---:|---:|---:|:-:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['shape']} | {r['res']} | {r['cell']:.4f} | {r['vertices']} | {'yes' if r['watertight'] else 'no'} | "
            f"{r['seconds']:.2f} | {r['mesh_to_surface']:.2e} | {r['surface_to_mesh']:.2e} | "
            f"{r['chamfer']:.2e} | {r['hausdorff']:.2e} |"
        )
    lines.append(END)
    return "\n".join(lines)


def write_section(path: Path, section: str) -> None:
    """Replace (or append) our marked section of ``path``, keeping everything else."""
    common.write_section(path, NAME, section)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--resolutions", type=int, nargs="+", default=[32, 64, 128, 256])
    p.add_argument("--samples", type=int, default=100_000, help="surface samples per direction")
    p.add_argument("--out", type=Path, default=ROOT / "BENCHMARKS.md")
    p.add_argument("--no-write", action="store_true", help="print the table only")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    info = common.machine_info()
    rows = run(sorted(args.resolutions), args.samples)
    cmd_args = ["--resolutions", *map(str, args.resolutions)]
    if args.samples != 100_000:
        cmd_args += ["--samples", str(args.samples)]
    section = table(rows, cmd_args, args.samples, info)
    print(section)
    for shape in {r["shape"] for r in rows}:
        ch = [r["chamfer"] for r in rows if r["shape"] == shape]
        if any(b >= a for a, b in itertools.pairwise(ch)):
            print(f"WARNING: Chamfer does not decrease with resolution for {shape}: {ch}", file=sys.stderr)
    if not args.no_write:
        write_section(args.out, section)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
