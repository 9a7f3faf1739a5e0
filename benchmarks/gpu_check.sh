#!/usr/bin/env bash
# The GPU check: <= 8 minutes on one GPU per part, in three parts (or all at once where nothing limits the carry).
#   tests: the CUDA tests (device placement, fp16/bf16 autocast, two-pass exactness, CLIP on CUDA, a tiny
#          pipeline on cuda) -> $RESULTS/gpu_tests.log;
#   bench: benchmarks/gpu.py on device=cuda: the paper-resolution job (preset=paper_res) on a selfie capture and
#          stylization at 512x512 with patch backprop (peak GPU memory) -> $RESULTS/gpu.json, gpu_bench.log
#          (on this machine, the GPU section of BENCHMARKS.md; elsewhere `python -m benchmarks gpu
#          --report-from gpu.json` writes it from the returned figures).
#   compiled: benchmarks/compiled.py on cuda (eager vs compiled field, frame, steps, compile time) ->
#          $RESULTS/compiled_cuda.json, compiled_cuda.md, compiled_cuda.log.
# $RESULTS is $OUT where set, else benchmarks/results.
# Usage (from the repo root):  bash benchmarks/gpu_check.sh [tests|bench|all] [DATA_ROOT]
#   DATA_ROOT holds fangzhou_nature/ (default ../shared/data). A machine without a package index gets the
#   wheels it lacks from .gpu_bundle/*/wheels (python -m benchmarks gpu_bundle writes them, and a compact
#   fangzhou_nature in .gpu_bundle/bench/data); they are installed into .gpu_site/, which the bench part
#   reuses when the tests part ran on the same machine before it.
set -euo pipefail
cd "$(dirname "$0")/.."
PART="${1:-all}"
DATA_ROOT="${2:-../shared/data}"
case "$PART" in tests|bench|compiled|all) ;; *) echo "usage: bash benchmarks/gpu_check.sh [tests|bench|compiled|all] [DATA_ROOT]" >&2; exit 2;; esac
RESULTS="${OUT:-benchmarks/results}"
mkdir -p "$RESULTS"
export PYTHONUNBUFFERED=1 PIP_DISABLE_PIP_VERSION_CHECK=1
shopt -s nullglob
wheels=()  # those not installed in .gpu_site yet (NAME-VERSION.dist-info)
for w in .gpu_bundle/*/wheels/*.whl; do
  IFS=- read -r name version _ <<< "$(basename "$w")"
  [ -d ".gpu_site/$name-$version.dist-info" ] || wheels+=("$w")
done
if [ ${#wheels[@]} -gt 0 ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --target .gpu_site "${wheels[@]}"
fi
if [ -d .gpu_site ]; then export PYTHONPATH="$PWD/.gpu_site:$PWD${PYTHONPATH:+:$PYTHONPATH}"; fi
missing=$(python3 -c "import importlib.util as u; print(' '.join(m for m in ('hydra', 'kornia', 'pydantic', 'imageio_ffmpeg') if u.find_spec(m) is None))")
if [ -n "$missing" ]; then
  echo "missing on this machine: $missing. Run 'python -m benchmarks gpu_bundle' where pip works and carry" \
       ".gpu_bundle/tests (the bench part reuses its install only on the same machine, right after it)." >&2
  exit 3
fi
python3 -c "import torch; assert torch.cuda.is_available(), 'no CUDA device: nothing to check'; print(torch.cuda.get_device_name(), torch.__version__)"
rc=0  # each part runs whatever the other gave; the exit status is the last failure's
if [ "$PART" = tests ] || [ "$PART" = all ]; then
  timeout 200 python3 -m pytest -q -p no:cacheprovider -m cuda tests/test_cuda.py 2>&1 | tee "$RESULTS/gpu_tests.log" || rc=$?
fi
if [ "$PART" = compiled ] || [ "$PART" = all ]; then
  timeout 300 python3 -m benchmarks compiled --device cuda --steps 10 --reps 5 --root "$RESULTS/compiled_root" \
    --raw "$RESULTS/compiled_cuda.json" --out "$RESULTS/compiled_cuda.md" 2>&1 | tail -n 40 | tee "$RESULTS/compiled_cuda.log" || rc=$?
fi
if [ "$PART" = bench ] || [ "$PART" = all ]; then
  timeout 480 python3 -m benchmarks gpu --data-root "$DATA_ROOT" --raw "$RESULTS/gpu.json" 2>&1 | tail -n 40 | tee "$RESULTS/gpu_bench.log" || rc=$?
fi
exit $rc
