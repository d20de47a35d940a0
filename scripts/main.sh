#!/usr/bin/env bash
# Set up, then run the main job on the embedded default (cpu profile): render the procedural denoising
# dataset and preprocess it. Extra arguments are Hydra overrides, e.g. `profile=smoke`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/python -m src.run "$@"
