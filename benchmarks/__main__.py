"""``python -m benchmarks NAME [options]``: run one benchmark (``python -m benchmarks`` lists them)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: modules of this package that are not benchmarks
NOT_BENCHMARKS = {"__init__", "__main__", "common"}


def benchmarks() -> list[str]:
    """The benchmark modules: every module here with a ``main(argv)``."""
    return sorted(p.stem for p in HERE.glob("*.py")
                  if p.stem not in NOT_BENCHMARKS and "\ndef main(" in p.read_text())


def first_line(name: str) -> str:
    doc = (importlib.import_module(f"benchmarks.{name}").__doc__ or "").strip()
    return doc.splitlines()[0] if doc else ""


def main(argv: list[str]) -> int:
    names = benchmarks()
    if not argv or argv[0] in ("-h", "--help"):
        width = max(map(len, names))
        print("usage: python -m benchmarks NAME [options]   (NAME --help: its options)\n")
        print("\n".join(f"  {n:<{width}}  {first_line(n)}" for n in names))
        return 0
    name = argv[0]
    if name not in names:
        print(f"error: no benchmark {name!r}; one of: {', '.join(names)}", file=sys.stderr)
        return 2
    return int(importlib.import_module(f"benchmarks.{name}").main(argv[1:]) or 0)


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
