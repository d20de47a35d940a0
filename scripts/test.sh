#!/usr/bin/env bash
# Set up, then lint and run the test suite (slow tests are excluded; add `-m slow` to run them).
# Two pytest-xdist workers (NRBENCH_TEST_WORKERS; 0 runs in one process), each taking whole test files, so a
# file's module fixtures are built once: most tests wait on subprocesses and imports, which two cores overlap.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check src tests hydra_plugins mlflow_plugins
.venv/bin/ruff format --check src tests hydra_plugins mlflow_plugins
.venv/bin/pytest -n "${NRBENCH_TEST_WORKERS:-2}" --dist loadfile "$@"
