"""The TensorVM grid's lookups as one fused CPU kernel (``csrc/tensorvm.cpp``), part of ``compile=auto|on``.

ATen's ``grid_sample`` reads a corner's components from C separate planes (channel-first) and the encoding then
multiplies, permutes and concatenates the looked-up planes and lines into [N, 3LC] features in further passes;
its backward parallelizes over the three planes only. The fused kernel reads channel-last planes (a corner's C
components contiguous) and writes each point's features in place, one pass over the points for what took
several; its backward goes plane by plane (a plane and its gradient are the working set) with a gradient
buffer per thread. Its arithmetic is ``grid_sample``'s (bilinear, aligned corners, zero padding): the features
equal the ATen path's up to float rounding, the gradients up to the order of their sums (tests/test_fused_grid.py);
a NaN point's features are NaN, as ATen's, and it adds nothing to the gradients (ATen's would write NaN).

:func:`nerfart_plugin.fields.compiled.apply_compile` switches it on with the compile, and on its own where the
compile would not pay (a short run: the kernel is built once per machine, so it costs nothing per run).

The kernel is plain C++ (no PyTorch headers) built once per machine with the system's C++ compiler into the
compile cache (``<compile cache>/nerfart_kernels``, see :func:`nerfart_plugin.fields.compiled.cache_dir`) and called
through ``ctypes`` from a ``torch.library`` custom op, so ``torch.compile`` keeps the field's query in one graph
around it. It serves float32 and float64 points on the CPU that need no gradient themselves (the finite-difference
normals and the training forward; an analytic SDF gradient differentiates the lookups twice and stays on ATen).
Where it cannot be built (no compiler) the encoding keeps ATen's lookups, with the reason logged once.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import subprocess
import tempfile
import threading
from pathlib import Path
from typing import Optional, Sequence

import torch
from torch import Tensor

log = logging.getLogger("nerfart_plugin")

SOURCE = Path(__file__).with_name("csrc") / "tensorvm.cpp"
#: the C++ compiler's flags (no fast-math nor contracted multiply-adds: the rounding of ATen's grid_sample)
FLAGS = ("-O3", "-march=native", "-ffp-contract=off", "-std=c++17", "-fPIC", "-shared", "-pthread")
ABI_VERSION = 1

_lock = threading.Lock()
_library: Optional[ctypes.CDLL] = None
_unavailable: Optional[str] = None  # why the kernel cannot be used here (set once, logged once)


def _cpu_signature() -> str:
    """What ``-march=native`` depends on: the CPU's model and flags (a cache shared by machines keeps one build
    per kind of CPU)."""
    try:
        info = Path("/proc/cpuinfo").read_text()
        lines = [ln for ln in info.splitlines() if ln.startswith(("model name", "flags"))][:2]
        return "\n".join(lines)
    except OSError:
        return platform.processor() or platform.machine()


def library_path(cxx: str) -> Path:
    """Where the kernel built by ``cxx`` for this CPU lives: a content hash of the source, the flags, the compiler's
    version and the CPU in the name, inside the compile cache."""
    from nerfart_plugin.fields.compiled import cache_dir

    version = subprocess.run([cxx, "--version"], capture_output=True, text=True, timeout=60).stdout
    key = hashlib.sha256("\n".join([SOURCE.read_text(), " ".join(FLAGS), version, _cpu_signature()]).encode())
    return cache_dir() / "nerfart_kernels" / f"tensorvm-{key.hexdigest()[:16]}.so"


def _build(cxx: str, target: Path) -> None:
    """Compile the kernel into ``target`` atomically (a temporary file renamed into place)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        done = subprocess.run([cxx, *FLAGS, str(SOURCE), "-o", tmp], capture_output=True, text=True, timeout=600)
        if done.returncode != 0:
            raise RuntimeError(f"{cxx} failed on {SOURCE}: {done.stderr.strip()[-800:]}")
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def load() -> Optional[ctypes.CDLL]:
    """The kernel library, built on first use (None where it cannot be: the reason is logged once and
    :func:`unavailable` returns it)."""
    global _library, _unavailable
    if _library is not None or _unavailable is not None:
        return _library
    with _lock:
        if _library is not None or _unavailable is not None:
            return _library
        from nerfart_plugin.fields import compiled  # (imports this module's package)

        cxx = compiled.cxx_compiler()
        if cxx is None:
            _unavailable = "no C++ compiler on the PATH (install g++ or clang++, or set CXX)"
        else:
            try:
                target = library_path(cxx)
                if not target.exists():
                    log.info("compile: building the fused grid kernel into %s", target)
                    _build(cxx, target)
                lib = ctypes.CDLL(str(target))
                if lib.tensorvm_abi_version() != ABI_VERSION:
                    raise RuntimeError(f"{target} is an older build; delete it to rebuild")
                _declare(lib)
                _library = lib
            except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
                _unavailable = f"the fused grid kernel could not be built or loaded ({exc})"
        if _unavailable:
            log.warning("compile: the grid's lookups stay ATen's: %s", _unavailable)
        return _library


def unavailable() -> Optional[str]:
    """Why the fused kernel is not used here (None: it is, or has not been asked for yet)."""
    return _unavailable


def _declare(lib: ctypes.CDLL) -> None:
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    for suffix in ("f32", "f64"):
        fwd = getattr(lib, f"tensorvm_forward_{suffix}")
        fwd.argtypes, fwd.restype = [p, i64, i32, p, p, p, i32, p, i32], None
        bwd = getattr(lib, f"tensorvm_backward_{suffix}")
        bwd.argtypes, bwd.restype = [p, i64, i32, p, p, p, i32, p, p, p, i32], None


_SUFFIX = {torch.float32: "f32", torch.float64: "f64"}


def serves(xn: Tensor) -> bool:
    """Whether the fused kernel serves these points (the planes cast to their dtype): on the CPU, float32 or
    float64, without a gradient of their own, and the kernel loaded (:func:`load`)."""
    return _library is not None and xn.device.type == "cpu" and xn.dtype in _SUFFIX and not xn.requires_grad


def _pointers(tensors: Sequence[Tensor]) -> ctypes.Array:
    return (ctypes.c_void_p * len(tensors))(*[t.data_ptr() for t in tensors])


def _sides(planes: Sequence[Tensor]) -> ctypes.Array:
    return (ctypes.c_int64 * len(planes))(*[int(p.shape[1]) for p in planes])


@torch.library.custom_op("nerfart::tensorvm_features", mutates_args=())
def tensorvm_features(xn: Tensor, planes: list[Tensor], lines: list[Tensor]) -> Tensor:
    """Features [N, 3LC] of points ``xn`` [N,3] in [-1,1] from channel-last ``planes`` (per level [3,r,r,C]) and
    ``lines`` ([3,r,C]); see the module docstring."""
    xn = xn.contiguous()
    planes = [p.contiguous() for p in planes]
    lines = [ln.contiguous() for ln in lines]
    n, levels, c = xn.shape[0], len(planes), int(planes[0].shape[-1])
    out = xn.new_empty(n, 3 * levels * c)
    if n:
        fn = getattr(load(), f"tensorvm_forward_{_SUFFIX[xn.dtype]}")
        fn(xn.data_ptr(), n, levels, _sides(planes), _pointers(planes), _pointers(lines), c, out.data_ptr(),
           torch.get_num_threads())
    return out


@tensorvm_features.register_fake
def _(xn: Tensor, planes: list[Tensor], lines: list[Tensor]) -> Tensor:
    return xn.new_empty(xn.shape[0], 3 * len(planes) * planes[0].shape[-1])


@torch.library.custom_op("nerfart::tensorvm_features_backward", mutates_args=())
def tensorvm_features_backward(grad: Tensor, xn: Tensor, planes: list[Tensor],
                               lines: list[Tensor]) -> tuple[list[Tensor], list[Tensor]]:
    """The gradients of :func:`tensorvm_features` with respect to its planes and lines (same layouts)."""
    grad, xn = grad.contiguous(), xn.contiguous()
    planes = [p.contiguous() for p in planes]
    lines = [ln.contiguous() for ln in lines]
    gplanes = [torch.zeros_like(p) for p in planes]
    glines = [torch.zeros_like(ln) for ln in lines]
    n, levels, c = xn.shape[0], len(planes), int(planes[0].shape[-1])
    if n:
        fn = getattr(load(), f"tensorvm_backward_{_SUFFIX[xn.dtype]}")
        fn(xn.data_ptr(), n, levels, _sides(planes), _pointers(planes), _pointers(lines), c, grad.data_ptr(),
           _pointers(gplanes), _pointers(glines), torch.get_num_threads())
    return gplanes, glines


@tensorvm_features_backward.register_fake
def _(grad: Tensor, xn: Tensor, planes: list[Tensor], lines: list[Tensor]) -> tuple[list[Tensor], list[Tensor]]:
    return [torch.empty_like(p) for p in planes], [torch.empty_like(ln) for ln in lines]


def _setup_context(ctx, inputs, output) -> None:  # noqa: ANN001 (torch.library's signature)
    xn, planes, lines = inputs
    ctx.save_for_backward(xn, *planes, *lines)
    ctx.levels = len(planes)


def _backward(ctx, grad: Tensor):  # noqa: ANN001, ANN202
    xn, *rest = ctx.saved_tensors
    planes, lines = rest[:ctx.levels], rest[ctx.levels:]
    gplanes, glines = tensorvm_features_backward(grad, xn, list(planes), list(lines))
    return None, gplanes, glines


tensorvm_features.register_autograd(_backward, setup_context=_setup_context)


def channel_last(planes: Tensor, lines: Tensor) -> tuple[Tensor, Tensor]:
    """Views of one level's ``planes`` [3,C,r,r] and ``lines`` [3,C,r,1] as the kernel's [3,r,r,C] and [3,r,C]
    (no copy when the parameters are stored channels-last, see ``TensorVMGridEncoding.set_fused``)."""
    return planes.permute(0, 2, 3, 1), lines.permute(0, 2, 3, 1)[:, :, 0, :]
