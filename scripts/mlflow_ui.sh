#!/usr/bin/env bash
# MLflow's UI on this project's runs. Extra arguments go to `mlflow ui` (e.g. --port 5001, --workers 2).
#
# Which view an experiment opens on: MLflow 3.17's UI decides it from the browser's sidebar switch
# "GenAI | Model training" (kept in the browser's localStorage, GenAI until picked), not from the
# experiment, so in a fresh browser every experiment opened on its GenAI overview ("Traces 0"). Hence
# MLflow's server with this repo's app plugin (mlflow_plugins/nrbench_runs_view, `--app-name nrbench`):
# MLflow's own app whose page stores "Model training" in a browser that has not picked a view; a browser
# that picked GenAI keeps it. Checked in headless Chromium with MLflow 3.17: tests/test_mlflow_ui.py.
#
# Start-up on a small machine: `mlflow ui` starts 4 web workers and 7 job-runner processes (GenAI
# scorers, evaluation, prompt optimisation; none of which this harness uses), each importing MLflow, so on
# 2 shared cores the UI answered after ~30 s. Here: one web worker per 4 cores (1 to 4; a worker serves a
# browser's parallel requests on its threads) and the job runner off unless MLFLOW_SERVER_ENABLE_JOB_EXECUTION
# says otherwise.
set -euo pipefail
cd "$(dirname "$0")/.."
uri="${MLFLOW_TRACKING_URI:-sqlite:///$PWD/mlflow.db}"
export MLFLOW_SERVER_ENABLE_JOB_EXECUTION="${MLFLOW_SERVER_ENABLE_JOB_EXECUTION:-false}"
cores=$(nproc 2>/dev/null || echo 1)
workers=$((cores / 4))
workers=$((workers < 1 ? 1 : workers > 4 ? 4 : workers))
port=5000
own_workers=(--workers)   # emptied when the caller passes its own --workers (then named in the line below)
own_app=(--app-name nrbench)   # emptied when the caller names an app
args=("$@")
for ((i = 0; i < ${#args[@]}; i++)); do
  case "${args[i]}" in
    --port | -p) if ((i + 1 < ${#args[@]})); then port="${args[i + 1]}"; fi ;;
    --port=*) port="${args[i]#--port=}" ;;
    --workers | -w) if ((i + 1 < ${#args[@]})); then workers="${args[i + 1]}"; fi; own_workers=() ;;
    --workers=*) workers="${args[i]#--workers=}"; own_workers=() ;;
    --app-name | --app-name=*) own_app=() ;;
  esac
done
if ((${#own_workers[@]})); then own_workers+=("$workers"); fi
echo "mlflow ui: $uri, $workers worker(s) for $cores core(s), job runner" \
  "$([[ $MLFLOW_SERVER_ENABLE_JOB_EXECUTION == false ]] && echo off || echo on) -> open http://127.0.0.1:$port/#/experiments"
echo "  $([[ ${#own_app[@]} -gt 0 ]] && echo "experiments open on their runs (the sidebar's" \
  "GenAI | Model training switch: Model training until picked)" || echo "the caller's app: MLflow opens" \
  "experiments on the sidebar's GenAI | Model training switch, GenAI until picked"); a job's run URL opens its run"
exec .venv/bin/mlflow ui --backend-store-uri "$uri" --host 127.0.0.1 --port "$port" "${own_workers[@]}" \
  "${own_app[@]}" "$@"
