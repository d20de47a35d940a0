#!/usr/bin/env bash
# Set up, then lint and run the test suite (slow tests are excluded; add `-m slow` to run them).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check src tests hydra_plugins mlflow_plugins
.venv/bin/ruff format --check src tests hydra_plugins mlflow_plugins
.venv/bin/pytest "$@"
