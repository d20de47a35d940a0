#!/usr/bin/env bash
# Set up, then run the main job on the embedded default (cpu profile): render and preprocess the
# procedural denoising dataset, then train and evaluate KPCN, DPCN and residual KPCN as one Hydra
# multirun (one MLflow run each, under a parent run) and print their comparison table.
# Arguments replace the default job, e.g. `bash scripts/main.sh profile=smoke` or
# `bash scripts/main.sh -m model=cross_bilateral,oidn`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
if [ "$#" -eq 0 ]; then
  set -- -m model=kpcn,dpcn,resnet
fi
.venv/bin/python -m src.run "$@"
