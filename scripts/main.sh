#!/usr/bin/env bash
# Set up, then run the main job: the whole study as the DVC pipeline (`dvc repro`, dvc.yaml) at the
# profile params.yaml names (cpu): render and preprocess the denoising data, train and evaluate every
# denoiser and baseline, render the NeRF scenes, train and evaluate every NeRF variant per scene, and write
# both reports to reports/. A second run redoes only what a change affected.
# Arguments run one Hydra job instead, e.g. `bash scripts/main.sh profile=smoke` or
# `bash scripts/main.sh -m +sweep=whitening`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
if [ "$#" -eq 0 ]; then
  PATH="$PWD/.venv/bin:$PATH" exec dvc repro   # stages call `python`: the project's environment
fi
exec .venv/bin/python -m src.run "$@"
