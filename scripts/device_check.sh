#!/usr/bin/env bash
# The device check (issue 46): the cost cards of the benches on a lent GPU, in one run of about 6 minutes
# (every step has its own time limit; the sum of the limits is 8 minutes).
#
#   bash scripts/device_check.sh [OUT]          # on the device machine: bash scripts/device_check.sh "$OUT"
#
# Writes under OUT (default device_check/):
#   device.txt                 nvidia-smi's GPU, driver and memory; torch, CUDA and cuDNN versions
#   denoise_fp32.txt           the denoise bench at WIDTHxHEIGHT (U-Net KPCN, KPCN, OIDN, the reference
#   denoise_tf32.txt           conv2d) in strict fp32, in TF32 (convolutions and matmuls) and under bf16
#   denoise_bf16.txt           autocast: s/frame, GFLOP/frame, GFLOP/s, % of the reference conv2d (the
#                              device's measured peak at that precision), peak host and GPU memory
#   nerf.txt, nerf_bf16.txt    the NeRF step bench at the NERF_PROFILE sizes (paper: the published batch
#                              and network sizes): training rays/s and GFLOP/s, rendering rays/s
#   cards.md                   all of the above, one section each: what docs/benchmark.md's GPU tables
#                              are copied from
#   failures.txt               only when a step failed or ran out of its time (its output file says why)
#   mlflow.db                  the denoise bench runs (experiment nrbench-bench), which a report on the
#                              same store reads the peak from (src/report/cost_card.py)
#
# Settings (environment): DEVICE (cuda), WIDTH, HEIGHT (1280, 720), ROUNDS (7), MODELS (unet_kpcn,kpcn),
# NERF_PROFILE (paper), NERF_MODELS (nerf,mipnerf,refnerf), NERF_STEPS (20), PYTHON (python). The test
# suite runs it on the CPU with a tiny frame and fewer models (tests/test_device_check.py) to check its
# plumbing; only a GPU gives its numbers meaning.
set -uo pipefail

OUT=${1:-${OUT:-device_check}}
DEVICE=${DEVICE:-cuda}
WIDTH=${WIDTH:-1280}
HEIGHT=${HEIGHT:-720}
ROUNDS=${ROUNDS:-7}
MODELS=${MODELS:-unet_kpcn,kpcn}
NERF_MODELS=${NERF_MODELS:-nerf,mipnerf,refnerf}
NERF_PROFILE=${NERF_PROFILE:-paper}
NERF_STEPS=${NERF_STEPS:-20}
PYTHON=${PYTHON:-python}

mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
export MLFLOW_TRACKING_URI="sqlite:///$OUT/mlflow.db"
rm -f "$OUT/failures.txt"
started=$(date +%s)

step() {  # step NAME SECONDS COMMAND...: run it under its limit, output to OUT/NAME.txt
    local name=$1 limit=$2
    shift 2
    echo "== $name (limit ${limit} s)"
    timeout "$limit" "$@" >"$OUT/$name.txt" 2>&1
    local status=$?
    if [ $status -ne 0 ]; then
        echo "$name: exit status $status (124: over its ${limit} s); see $name.txt" | tee -a "$OUT/failures.txt"
    fi
}

{
    nvidia-smi --query-gpu=name,memory.total,driver_version,compute_cap --format=csv 2>/dev/null ||
        echo "nvidia-smi: not available (no NVIDIA GPU here)"
    "$PYTHON" -c 'import torch; print("torch", torch.__version__, "CUDA", torch.version.cuda, "cuDNN",
torch.backends.cudnn.version(), "GPU", torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none")'
} >"$OUT/device.txt" 2>&1

denoise=("$PYTHON" -m src.bench denoise --device "$DEVICE" --width "$WIDTH" --height "$HEIGHT"
    --rounds "$ROUNDS" --warmup 2 --models "$MODELS" --oidn --log)
step denoise_fp32 100 "${denoise[@]}" --tf32 off
step denoise_tf32 100 "${denoise[@]}" --tf32 on
step denoise_bf16 100 "${denoise[@]}" --autocast bf16
nerf=("$PYTHON" -m src.bench nerf --device "$DEVICE" --profile "$NERF_PROFILE" --models "$NERF_MODELS"
    --steps "$NERF_STEPS")
step nerf 90 "${nerf[@]}"
step nerf_bf16 90 "${nerf[@]}" --autocast bf16

{
    echo "# Device check: cost cards"
    echo
    echo "Run $(date -u +%Y-%m-%dT%H:%M:%SZ), commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown)."
    for name in device denoise_fp32 denoise_tf32 denoise_bf16 nerf nerf_bf16; do
        echo
        echo "## $name"
        echo
        echo '```'
        cat "$OUT/$name.txt"
        echo '```'
    done
} >"$OUT/cards.md"

echo "device check: $(($(date +%s) - started)) s -> $OUT/cards.md"
[ ! -f "$OUT/failures.txt" ]
