"""python -m benchmarks mesh_extraction: a tiny run writes only its own BENCHMARKS.md section."""

from __future__ import annotations

import importlib


def _load():
    return importlib.import_module("benchmarks.mesh_extraction")


def test_benchmark_section_replaced_and_rest_preserved(tmp_path):
    bench = _load()
    out = tmp_path / "BENCHMARKS.md"
    out.write_text(f"# Benchmarks\n\nintro\n\n{bench.START}\nold table\n{bench.END}\n\n## other section\nkeep me\n")
    assert bench.main(["--resolutions", "16", "24", "--samples", "2000", "--out", str(out)]) == 0
    text = out.read_text()
    assert "old table" not in text and "intro" in text and "keep me" in text
    assert text.count(bench.START) == 1 and text.count(bench.END) == 1
    assert "`python -m benchmarks mesh_extraction --resolutions 16 24 --samples 2000`" in text
    rows = [line for line in text.splitlines() if line.startswith(("| sphere", "| torus"))]
    assert len(rows) == 4
    chamfer = [float(r.split("|")[9]) for r in rows]
    assert chamfer[1] < chamfer[0] and chamfer[3] < chamfer[2]
    # Absent file: created.
    fresh = tmp_path / "new.md"
    bench.main(["--resolutions", "16", "--samples", "500", "--out", str(fresh)])
    assert fresh.read_text().startswith("# Benchmarks") and bench.END in fresh.read_text()
