#!/usr/bin/env bash
# MLflow's UI on this project's runs, opened on its model-training view.
# MLflow 3's UI starts on its GenAI view (traces, prompts) unless the browser chose otherwise before; the
# URL's ?workflowType=machine_learning opens the training runs instead (checked in headless Chromium with
# MLflow 3.17: tests/test_mlflow_ui.py). Extra arguments go to `mlflow ui` (e.g. --port 5001).
set -euo pipefail
cd "$(dirname "$0")/.."
uri="${MLFLOW_TRACKING_URI:-sqlite:///$PWD/mlflow.db}"
port=5000
args=("$@")
for ((i = 0; i < ${#args[@]}; i++)); do
  if [[ "${args[i]}" == "--port" && $((i + 1)) -lt ${#args[@]} ]]; then port="${args[i + 1]}"; fi
done
echo "mlflow ui: $uri -> open http://127.0.0.1:$port/#/experiments?workflowType=machine_learning"
exec .venv/bin/mlflow ui --backend-store-uri "$uri" --host 127.0.0.1 --port "$port" "$@"
