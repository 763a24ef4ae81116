#!/usr/bin/env bash
# Runs copilot4d_gpu.py on a GPU machine whose python3 holds PyTorch (and numpy, scipy, numba,
# pandas, pyarrow, pluggy, click, tqdm, jinja2, matplotlib) but not pcfbench: the package is
# assembled from the repository's folders as pyproject.toml maps them. Inputs in .gpu/ (see the
# script's docstring); figures in $OUT (default ./gpu-out).
set -euo pipefail
out=${OUT:-gpu-out}
mkdir -p "$out"
pk=$(mktemp -d)
cp -r bench "$pk/pcfbench" && cp -r methods "$pk/pcfbench/methods" && cp -r datasets "$pk/pcfbench/datasets"
export PYTHONPATH="$pk" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv || true
python3 docs/experiments/copilot4d_gpu.py --inputs .gpu --out "$out" "$@" 2>&1 | tee "$out/log.txt"
