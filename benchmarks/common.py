"""Helpers shared by the benchmark scripts in ``benchmarks/``.

* :func:`machine_info` / :func:`machine_line`: nproc, CPU model, torch version and
  threads, date and the load average when the benchmark started;
* :func:`write_section`: replace (or append) one script's section of a Markdown
  file, between ``<!-- NAME:start -->`` and ``<!-- NAME:end -->``, keeping the rest;
* :func:`add_common_args` / :func:`output_paths`: ``--quick``, ``--out``,
  ``--figures``, ``--no-write`` (quick runs go to a scratch file, never to
  BENCHMARKS.md unless ``--out`` says so);
* :func:`compose`: a Hydra-composed project config (plain dict) from overrides;
* :func:`run_child` / :func:`child_main` / :func:`limit_memory` / :func:`peak_rss`:
  one measurement in a fresh subprocess, so its peak RSS is its own.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import logging
import os
import platform
import re
import resource
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

ROOT = Path(__file__).resolve().parents[1]

from nerfart_plugin.utils.io import atomic_write_text

BENCHMARKS_MD = ROOT / "BENCHMARKS.md"
FIGURES = ROOT / "benchmarks" / "figures"
#: scratch folder of quick smoke runs (git-ignored; the tests point $NERFART_BENCH_SCRATCH at a tmp folder)
SCRATCH = Path(os.environ.get("NERFART_BENCH_SCRATCH", ROOT / "outputs" / "benchmarks"))
QUICK_OUT = SCRATCH / "BENCHMARKS.quick.md"
RAW_DIR = ROOT / "benchmarks" / "results"  # real runs: committed next to BENCHMARKS.md, so reports can be rebuilt
QUICK_RAW_DIR = SCRATCH / "quick"  # smoke runs: scratch, git-ignored
GiB = 1024**3


# --------------------------------------------------------------------------- machine
def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def pinned_cpus() -> Optional[list[int]]:
    """The CPUs this process is restricted to (``taskset``), or None when it may use all of them."""
    if not hasattr(os, "sched_getaffinity"):
        return None
    cpus = sorted(os.sched_getaffinity(0))
    return cpus if len(cpus) < (os.cpu_count() or len(cpus)) else None


def machine_info() -> dict[str, Any]:
    """What the section header states; call it at the START of a benchmark (load average then)."""
    import torch

    try:
        mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / GiB
    except (ValueError, OSError, AttributeError):
        mem = float("nan")
    return {
        "nproc": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "cpu": cpu_model(),
        "ram_gib": mem,
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "python": platform.python_version(),
        "date": _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"),
        "loadavg": os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3,
        "t0": time.perf_counter(),
        "pinned": pinned_cpus(),
        "cpu_count": os.cpu_count(),
    }


def machine_line(info: dict[str, Any]) -> str:
    la = info["loadavg"]
    gpu = f"GPU {info['cuda']}; " if info.get("cuda") else "CPU only; "
    total = info["total_s"] if "total_s" in info else time.perf_counter() - info["t0"]  # total_s: a saved run
    pin = (f" — this run was pinned with `taskset` to CPU {','.join(map(str, info['pinned']))} of "
           f"{info['cpu_count']}, so timings are single-core" if info.get("pinned") else "")
    return (f"Machine: {info['nproc']} CPUs (nproc{pin}), {info['cpu']}, {info['ram_gib']:.0f} GiB RAM; {gpu}"
            f"torch {info['torch']}, {info['threads']} torch threads; Python {info['python']}. "
            f"Run {info['date']}, total {total:.0f} s; load average at start {la[0]:.2f} / {la[1]:.2f} / {la[2]:.2f} "
            f"(1/5/15 min). Shared machine: timings are noisy.")


# --------------------------------------------------------------------------- sections
def markers(name: str) -> tuple[str, str]:
    return f"<!-- {name}:start -->", f"<!-- {name}:end -->"


def command(script: str, argv: Sequence[str]) -> str:
    """The exact command to reproduce, from the repository root (with the ``taskset`` pinning it ran under):
    ``python -m benchmarks NAME ...`` for the benchmark module ``script`` (``NAME`` or ``NAME.py``)."""
    cpus = pinned_cpus()
    pin = ["taskset", "-c", ",".join(map(str, cpus))] if cpus else []
    name = script.removesuffix(".py")
    return " ".join([*pin, "python", "-m", "benchmarks", name, *(shlex.quote(a) for a in argv)])


def section(name: str, title: str, cmd: str, info: dict[str, Any], body: list[str], quick: bool) -> str:
    """A complete marked section: title, command, machine, then ``body`` lines."""
    start, end = markers(name)
    head = [start, f"## {title}" + (" — QUICK smoke run (not a result)" if quick else ""), ""]
    if quick:
        head += ["> **Quick mode** (`--quick`): tiny budgets and sizes to check that the script works. "
                 "These figures are NOT benchmark results.", ""]
    head += [f"Command (from the repo root): `{cmd}`  ", machine_line(info), ""]
    return "\n".join(head + body + [end])


def write_section(path: Path, name: str, text: str) -> None:
    """Replace (or append) the ``name`` section of ``path``, keeping everything else."""
    start, end = markers(name)
    path = Path(path)
    old = path.read_text() if path.exists() else "# Benchmarks\n"
    pattern = re.compile(re.escape(start) + r".*?" + re.escape(end), re.DOTALL)
    if pattern.search(old):
        new = pattern.sub(lambda _m: text, old)
    else:
        new = old.rstrip("\n") + "\n\n" + text + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, new)


def raw_path(name: str, quick: bool) -> Path:
    """Where a script's raw JSON results go: ``benchmarks/results/<name>.json`` for real runs (kept in
    the repository beside the ``BENCHMARKS.md`` they produced, so a report can be re-ranked or
    re-plotted later without re-running); quick smoke runs use ``outputs/benchmarks/quick/`` so they
    never overwrite a real run's raw results."""
    d = QUICK_RAW_DIR if quick else RAW_DIR
    d.mkdir(parents=True, exist_ok=True)
    return d / f"{name}.json"


def md_table(headers: Sequence[str], rows: Sequence[Sequence[Any]], align: Optional[str] = None) -> list[str]:
    """Markdown table lines; ``align`` one char per column: l, r or c (default: first l, rest r)."""
    align = align or ("l" + "r" * (len(headers) - 1))
    sep = {"l": "---", "r": "---:", "c": ":-:"}
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join(sep[a] for a in align) + "|"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return lines


def fmt(v: Any, spec: str = ".2f", none: str = "–") -> str:
    if v is None or (isinstance(v, float) and v != v):
        return none
    return format(v, spec) if isinstance(v, (int, float)) else str(v)


# --------------------------------------------------------------------------- arguments
def add_common_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true",
                   help="tiny smoke version (< 2 min); writes to a scratch file unless --out is given")
    p.add_argument("--out", type=Path, default=None,
                   help=f"Markdown file to write the section into (default {BENCHMARKS_MD.name}; "
                        f"with --quick: {QUICK_OUT})")
    p.add_argument("--figures", type=Path, default=None,
                   help="folder for PNG figures (default benchmarks/figures; with --quick: next to --out)")
    p.add_argument("--no-write", action="store_true", help="print the section only")


def add_raw_args(p: argparse.ArgumentParser) -> None:
    """``--raw`` (the raw JSON results) and ``--report-only`` (rebuild the section from them)."""
    p.add_argument("--raw", type=Path, default=None, help="raw JSON results (default benchmarks/results/<name>.json)")
    p.add_argument("--report-only", action="store_true", help="rebuild the section from --raw without measuring")


def raw_results(args: argparse.Namespace, name: str, measure: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """With ``--report-only`` the raw results read back from ``--raw``; else ``measure()``, written there."""
    raw_file = args.raw or raw_path(name, args.quick)
    if args.report_only:
        return json.loads(Path(raw_file).read_text())
    raw = measure()
    Path(raw_file).write_text(json.dumps(raw, indent=1, default=str))
    return raw


def output_paths(args: argparse.Namespace) -> tuple[Path, Path]:
    """(markdown file, figures folder) for these arguments: figures go to ``benchmarks/figures`` only
    for the real ``BENCHMARKS.md``; any other ``--out`` (or ``--quick``) gets a ``figures/`` folder
    beside it, and ``--no-write`` (nothing written into a report) puts them beside the quick report,
    so a scratch report never replaces a committed figure."""
    out = Path(args.out if args.out is not None else (QUICK_OUT if args.quick else BENCHMARKS_MD))
    if getattr(args, "no_write", False):
        default_figs = QUICK_OUT.parent / "figures"
    elif out.resolve() == BENCHMARKS_MD.resolve():
        default_figs = FIGURES
    else:
        default_figs = out.parent / "figures"
    figs = args.figures if args.figures is not None else default_figs
    return Path(out), Path(figs)


def rel(path: Path, base: Path) -> str:
    """``path`` relative to ``base`` (the Markdown file's folder) for links, else absolute."""
    try:
        return os.path.relpath(Path(path).resolve(), Path(base).resolve())
    except ValueError:
        return str(Path(path).resolve())


def finish(args: argparse.Namespace, name: str, text: str) -> Path:
    """Print the section and write it (unless ``--no-write``); returns the Markdown path."""
    out, _ = output_paths(args)
    print(text)
    if not args.no_write:
        write_section(out, name, text)
        print(f"wrote section {name!r} of {out}")
    return out


def start_logging(logger: logging.Logger) -> dict[str, Any]:
    """A benchmark's start: INFO logging with times, the machine (:func:`machine_info`, read now), the
    project's and Lightning's chatter quietened (:func:`quiet_logs`), ``logger`` kept at INFO."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    info = machine_info()
    quiet_logs()
    logger.setLevel(logging.INFO)
    return info


def quiet_logs() -> None:
    """Keep the benchmark's own INFO lines; silence Lightning's banners and library warnings."""
    import logging
    import warnings

    import lightning  # noqa: F401  (configures its loggers on import; override them after)

    for name in ("lightning", "lightning.pytorch", "lightning.fabric", "lightning.pytorch.utilities.rank_zero",
                 "nerfart_plugin"):
        logging.getLogger(name).setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", category=UserWarning)
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    warnings.filterwarnings("ignore", category=FutureWarning)


# --------------------------------------------------------------------------- config
def compose(overrides: Sequence[str]) -> dict[str, Any]:
    """The project config composed by Hydra from ``conf/`` with ``overrides``, as a plain dict."""
    from hydra import compose as _compose
    from hydra import initialize_config_dir
    from omegaconf import OmegaConf

    from nerfart_plugin.config.compose import config_dir

    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        cfg = _compose("config", overrides=list(overrides))
    return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]


def trained_run(root: Path, overrides: Sequence[str]) -> Path:
    """The folder of the run ``overrides`` name in ``root`` (as the CLI takes them), trained or reused: the
    stylization where the command makes one, else the reconstruction (``stage=reconstruct``)."""
    from nerfart_plugin.config.compose import load_config
    from nerfart_plugin.config.overrides import normalize_overrides
    from nerfart_plugin.run.pipeline import run

    result = run(load_config(normalize_overrides([f"output_root={root}", *overrides])))
    return Path((result.get("stylization") or result["reconstruction"])["dir"])


def shared_data() -> Path:
    """``../shared/data`` next to the repository (or $NERFART_SHARED_DATA)."""
    return Path(os.environ.get("NERFART_SHARED_DATA", ROOT.parent / "shared" / "data")).resolve()


# --------------------------------------------------------------------------- isolated measurements
def _status_kib(key: str) -> Optional[int]:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


def peak_rss() -> int:
    """Peak resident set size of this process, bytes: VmHWM (resettable, see :func:`reset_peak_rss`),
    else ``getrusage`` ru_maxrss (peak since the process started)."""
    hwm = _status_kib("VmHWM")
    if hwm is not None:
        return hwm * 1024
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(r) * (1 if sys.platform == "darwin" else 1024)


def reset_peak_rss() -> int:
    """Reset the peak-RSS mark to the current RSS (Linux: ``5`` into /proc/self/clear_refs) and return
    the current RSS in bytes: the baseline of a measurement. Without the reset the baseline is the
    peak so far (a transient peak during setup then hides smaller ones)."""
    import gc

    gc.collect()
    try:  # give freed heap back to the OS, so later allocations show up in RSS instead of reusing it
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    try:
        Path("/proc/self/clear_refs").write_text("5")
        cur = _status_kib("VmRSS")
        if cur is not None:
            return cur * 1024
    except OSError:
        pass
    return peak_rss()


def limit_memory(extra_bytes: float) -> Optional[float]:
    """Cap this process's address space at its current size + ``extra_bytes`` (RLIMIT_AS, Linux).

    Allocations beyond it fail with a RuntimeError/MemoryError instead of pushing a
    shared machine into swap. Returns the cap in bytes (None if not supported).
    """
    try:
        vm = next(int(l.split()[1]) * 1024 for l in Path("/proc/self/status").read_text().splitlines()
                  if l.startswith("VmSize:"))
    except (OSError, StopIteration):
        return None
    cap = int(vm + extra_bytes)
    resource.setrlimit(resource.RLIMIT_AS, (cap, resource.RLIM_INFINITY))
    return float(cap)


def is_oom(exc: BaseException) -> bool:
    msg = str(exc).lower()
    return isinstance(exc, MemoryError) or "out of memory" in msg or "can't allocate memory" in msg \
        or "cannot allocate memory" in msg or "failed to allocate" in msg


def run_child(script: Path, payload: dict[str, Any], timeout: float) -> dict[str, Any]:
    """Run ``python -m benchmarks <script's name> --child JSON`` (from the repository root) and return the dict it
    prints on a ``RESULT {...}`` line.

    On timeout returns ``{"status": "timeout"}``; on a crash ``{"status": "error", "error": ...}``.
    """
    cmd = [sys.executable, "-m", "benchmarks", Path(script).stem, "--child", json.dumps(payload)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=str(ROOT))
    except subprocess.TimeoutExpired:
        return {"status": "timeout"}
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    return {"status": "error", "error": " / ".join(tail) or f"exit code {proc.returncode}"}


def child_main(fn: Callable[[dict[str, Any]], dict[str, Any]], payload_json: str) -> int:
    """Body of ``--child``: run ``fn(payload)`` and print its result as ``RESULT {json}``."""
    import logging

    logging.basicConfig(level=logging.WARNING)
    payload = json.loads(payload_json)
    try:
        result = {"status": "ok", **fn(payload)}
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which labels the row
        result = {"status": "oom" if is_oom(exc) else "error", "error": f"{type(exc).__name__}: {exc}"[:300]}
    print("RESULT " + json.dumps(result), flush=True)
    return 0
