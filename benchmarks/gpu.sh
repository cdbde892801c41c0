#!/bin/sh
# The GPU measurements of issue 19: 256², 1024² and 2048² frames and a 600-frame sequence of a model with
# the CUDA variant (benchmarks/speed.py under MIFACERF_VARIANT=cuda_ad_rgb), written as JSON and a table.
#
#   benchmarks/gpu.sh MODEL [OUT.json]              # CONFIGS=exact,sh4,pca8 to add compressed rows
#
# Needs an NVIDIA GPU and a Mitsuba build with the cuda_ad_rgb variant; it stops with the variant's own
# error message otherwise. The project never needs a GPU: every other command runs on llvm_ad_rgb.
set -eu
MODEL=${1:?usage: benchmarks/gpu.sh MODEL [OUT.json]}
OUT=${2:-gpu-speed.json}
HERE=$(cd "$(dirname "$0")" && pwd)
PY=${PYTHON:-$HERE/../.venv/bin/python}
[ -x "$PY" ] || PY=python
export MIFACERF_VARIANT=${MIFACERF_VARIANT:-cuda_ad_rgb}
"$PY" -c "from mifacerf.variant import ensure_variant; print('variant', ensure_variant().variant())"
command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || true
exec "$PY" "$HERE/speed.py" "$MODEL" --configs "${CONFIGS:-exact}" --sizes 256,1024,2048 --frames "${FRAMES:-5}" \
    --sequence "${SEQUENCE:-600}" --sequence-config "${SEQUENCE_CONFIG:-exact}" --cold --json "$OUT"
