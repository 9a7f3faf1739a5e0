"""Compiled field evaluation (the ``compile`` setting): a field's ``query`` through ``torch.compile``.

What is compiled is each leaf field's ``query`` (encoding, MLPs, the SDF-to-colour step), once per field class,
with dynamic shapes (the renderer's sample counts vary per block and batch). The compiler fuses the elementwise
work (the softplus, the concatenations, the sigmoid, the finite-difference taps); the matrix products stay the
BLAS's. The TensorVM grid's lookups, which the compiler would decompose into slower gathers, run on a CPU as a
fused kernel of this package (:mod:`nerfart_plugin.fields.fused_grid`, one pass per point forward, a
plane-by-plane scatter backward, called from inside the compiled graph) and elsewhere (CUDA) as ATen's
``grid_sample`` (``encodings._grid_lookup``). With the fields, the occupancy grid's lookups along the rays and
the sampler's sections are compiled too (``OccupancyGrid.compiled``): the sampler's share of a render.

Callers evaluate a field through :func:`evaluate` (the renderer and the composite field do): a field whose
``compiled`` flag is set runs the compiled query, others their own. A compile that fails (a custom field the
compiler cannot trace, a platform without a working compiler) logs why once and leaves that field eager; the
results are the eager ones up to float rounding (tests/test_compiled.py).

The compiled kernels are cached on disk (:func:`use_cache_dir`: ``$NERFART_COMPILE_CACHE``, else
``~/.cache/nerfart_plugin/inductor``; inductor's kernels and, in ``nerfart_kernels/``, the fused grid kernel), so
a second process pays a fraction of the first one's compile time. Delete that folder to clear it.
"""

from __future__ import annotations

import logging
import os
import platform
import shutil
import time
from pathlib import Path
from typing import Any, Callable, Optional

import torch
from torch import Tensor, nn

from nerfart_plugin.errors import ConfigError
from nerfart_plugin.fields.field import Field
from nerfart_plugin.fields.occupancy import OccupancyGrid

log = logging.getLogger("nerfart_plugin")

#: the compiled ``query`` of each field class (the field instance is an argument, so copies share it)
_COMPILED: dict[type, Callable[..., dict[str, Tensor]]] = {}

#: training steps below which ``compile=auto`` stays eager, per stage: the compile (seconds; about half a minute
#: with a cold kernel cache on a CPU) against what each step saves (BENCHMARKS.md, "A compiled field": a few
#: milliseconds of a reconstruction step, a few hundred of a stylization step)
MIN_COMPILED_STEPS = {"reconstruction": 2000, "stylization": 50}

#: video frames below which ``compile=auto`` renders eager (stage=render)
MIN_COMPILED_FRAMES = 60

#: environment variable naming the compile cache folder
CACHE_ENV = "NERFART_COMPILE_CACHE"


def cache_dir() -> Path:
    """Where inductor keeps the compiled kernels between runs: ``$NERFART_COMPILE_CACHE``, else
    ``~/.cache/nerfart_plugin/inductor``."""
    return Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "nerfart_plugin" / "inductor").expanduser()


def use_cache_dir() -> Path:
    """Point inductor's on-disk cache at :func:`cache_dir` (unless ``TORCHINDUCTOR_CACHE_DIR`` is set already)."""
    folder = Path(os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(cache_dir())))
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def cxx_compiler() -> Optional[str]:
    """The C++ compiler on the PATH ($CXX first, then c++, g++, clang++), or None."""
    return next((c for c in (os.environ.get("CXX"), "c++", "g++", "clang++") if c and shutil.which(c)), None)


def compiler_missing(device: torch.device) -> Optional[str]:
    """Why ``torch.compile`` cannot run on ``device`` here (None: it can): inductor needs a C++ compiler for CPU
    kernels and Triton for CUDA ones, and does not support Windows."""
    if platform.system() == "Windows":
        return "torch.compile's inductor does not support Windows"
    if device.type == "cuda":
        try:
            import triton  # noqa: F401
        except ImportError:
            return "Triton is not installed (pip install triton)"
        return None
    if device.type == "cpu":
        return None if cxx_compiler() else "no C++ compiler on the PATH (install g++ or clang++, or set CXX)"
    return f"inductor does not compile for {device.type}"


def decide_compile(setting: str, device: torch.device, work: Optional[int] = None, minimum: int = 0,
                   unit: str = "steps") -> tuple[bool, str]:
    """Whether to compile the fields (``compile`` = on | off | auto) and the reason, as recorded in
    ``metrics.json["auto"]["compile"]``. ``auto``: on where a compiler is available and the work is long enough
    to pay for the compile (``work`` >= ``minimum`` ``unit``: training steps, video frames; None: it always is)."""
    if setting == "off":
        return False, "off"
    missing = compiler_missing(device)
    if setting == "on":
        if missing:
            raise ConfigError(f"compile=on: {missing}. Use compile=auto (compiles where it can) or compile=off.")
        return True, "on"
    if missing:
        return False, f"off ({missing})"
    if work is not None and work < minimum:
        return False, f"off ({work} {unit} < {minimum}: the compile would not pay)"
    return True, "on"


def compilable_fields(module: nn.Module) -> list[Field]:
    """The fields inside ``module`` whose ``query`` may be compiled (``Field.compilable``: not a composite, which
    evaluates its parts, nor a field that takes autograd inside its query)."""
    return [m for m in module.modules() if isinstance(m, Field) and m.compilable]


def set_compiled(module: nn.Module, on: bool = True) -> int:
    """Set the ``compiled`` flag of every :func:`compilable_fields` inside ``module`` (a field, a renderer, a
    system); returns how many (an SDF field with the analytic gradient is not among them: it stays eager). The
    compile itself happens at each field class's first compiled evaluation (and once more per grad mode)."""
    if on:
        use_cache_dir()
    fields = compilable_fields(module)
    for f in fields:
        f.compiled = on
        use_fused_kernels(f, on)
    for m in module.modules():  # the occupancy grid's lookups along the rays (the sampler's share of a render)
        if isinstance(m, OccupancyGrid):
            m.compiled = on and bool(fields)
    return len(fields)


def use_fused_kernels(module: nn.Module, on: bool = True) -> int:
    """Switch the encodings inside ``module`` that have a fused kernel of their own (the TensorVM grid's
    lookups, :mod:`nerfart_plugin.fields.fused_grid`) to it or back to ATen's; returns how many use it now."""
    count = 0
    for m in module.modules():
        if hasattr(m, "set_fused"):
            m.set_fused(on)
            count += int(m.fused)
    return count


def apply_compile(module: nn.Module, setting: str, device: torch.device, work: Optional[int] = None,
                  minimum: int = 0, unit: str = "steps") -> str:
    """Compile the fields inside ``module`` as :func:`decide_compile` says and return what was chosen, as
    ``metrics.json["auto"]["compile"]`` records it. Where the compile would not pay (short work) the grid's
    lookups still take the fused kernel (built once per machine, no per-run cost): the choice then ends in
    "; grid lookups fused". ``compile=off`` leaves everything to PyTorch's own kernels."""
    on, choice = decide_compile(setting, device, work, minimum, unit)
    if on and set_compiled(module, True) == 0:
        choice = "off (no field here can be compiled: an analytic SDF gradient stays eager)"
    if not on:
        set_compiled(module, False)
        # no compiler: decide_compile has said so already (and the kernel's loader would warn again)
        if setting != "off" and compiler_missing(device) is None and use_fused_kernels(module, True):
            choice += "; grid lookups fused"
    return choice


def compiled_query(cls: type) -> Callable[..., dict[str, Tensor]]:
    """``cls.query`` through ``torch.compile`` (dynamic shapes), made once per field class."""
    fn = _COMPILED.get(cls)
    if fn is None:
        fn = _COMPILED[cls] = torch.compile(cls.query, dynamic=True)
    return fn


def evaluate(field: nn.Module, x: Tensor, d: Tensor, with_normal: bool = True) -> dict[str, Tensor]:
    """``field.query(x, d, with_normal)``, compiled when the field's ``compiled`` flag is set (see the module
    docstring); a field whose compile fails is evaluated eagerly from then on, with the reason logged once."""
    if not getattr(field, "compiled", False) or x.shape[0] < 2:
        return field.query(x, d, with_normal=with_normal)
    return _compiled_or_eager(field, x, d, with_normal)


def _compiled_or_eager(field: nn.Module, x: Tensor, d: Tensor, with_normal: bool) -> dict[str, Tensor]:
    """The compiled query of ``field``; on a compiler failure the eager one, the field marked uncompiled."""
    try:
        return compiled_query(type(field))(field, x, d, with_normal=with_normal)
    except torch._dynamo.exc.TorchDynamoException as exc:  # the compiler's own failures (a field's errors recur eager)
        field.compiled = False
        log.warning("compile: %s is evaluated uncompiled: the compiler failed (%s: %s)", type(field).__name__,
                    type(exc).__name__, str(exc).splitlines()[0][:300] if str(exc) else "")
        return field.query(x, d, with_normal=with_normal)


def warm_up(field: nn.Module, device: Any, with_normal: bool = False) -> float:
    """Compile the no-grad query of the compilable fields in ``field`` now (a few points), whatever their
    ``compiled`` flag, e.g. in a viewer's background thread while it serves eager frames (which use the fused
    kernels from then on); returns the seconds."""
    t0 = time.perf_counter()
    x = torch.zeros(64, 3, device=device)
    d = torch.nn.functional.normalize(torch.ones(64, 3, device=device), dim=-1)
    with torch.no_grad():
        for f in compilable_fields(field):
            use_fused_kernels(f, True)  # built here, off the caller's thread, and traced into the graph
            _compiled_or_eager(f, x, d, with_normal)
    return time.perf_counter() - t0
