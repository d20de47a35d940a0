#!/bin/bash
# A one-node SLURM cluster and an MLflow tracking server on this machine, for the tests and for trying
# `hydra/launcher=slurm` on a laptop (docs/studies.md, "A cluster on one machine").
#
#   bash scripts/cluster.sh up      # start munge, slurmctld, slurmd and `mlflow server`; print the env file
#   bash scripts/cluster.sh down    # stop everything `up` started (also what a failed `up` left)
#   bash scripts/cluster.sh status  # what runs
#   source "$NRBENCH_CLUSTER_DIR/cluster.env"   # SLURM_CONF and MLFLOW_TRACKING_URI for the commands after
#
# Debian's slurm-wlm (22.05) and munge, installed with apt-get where missing; run as root (slurmctld and
# slurmd run as root here, as on a test node). The node is sized to the machine (its CPUs, and its
# memory minus 1 GB), one partition `debug`; accounting is off. State, logs, the tracking server's
# SQLite store and artifacts live under NRBENCH_CLUSTER_DIR (default /tmp/nrbench-cluster).
# NRBENCH_MLFLOW_PORT picks the server's port (default 5071).
set -euo pipefail

DIR=${NRBENCH_CLUSTER_DIR:-/tmp/nrbench-cluster}
PORT=${NRBENCH_MLFLOW_PORT:-5071}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
MLFLOW=${NRBENCH_MLFLOW:-$ROOT/.venv/bin/mlflow}
HOST=$(hostname -s)

fail() { echo "cluster: $*" >&2; exit 2; }

install_missing() {
    command -v slurmctld >/dev/null && command -v munged >/dev/null && return
    [ "$(id -u)" = 0 ] || fail "slurm-wlm and munge are missing; install them (apt-get install slurm-wlm munge) or run as root"
    echo "cluster: installing slurm-wlm and munge (apt-get)"
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q slurm-wlm munge >"$DIR/apt.log" 2>&1 \
        || { apt-get update -q >>"$DIR/apt.log" 2>&1 && DEBIAN_FRONTEND=noninteractive apt-get install -y -q slurm-wlm munge >>"$DIR/apt.log" 2>&1; } \
        || fail "apt-get install slurm-wlm munge failed; see $DIR/apt.log"
}

start_munge() {
    mkdir -p /etc/munge /run/munge /var/lib/munge /var/log/munge
    if [ ! -s /etc/munge/munge.key ]; then
        head -c 1024 /dev/urandom > /etc/munge/munge.key
    fi
    chown -R munge:munge /etc/munge /run/munge /var/lib/munge /var/log/munge
    chmod 400 /etc/munge/munge.key
    chmod 755 /run/munge
    if ! munge -n >/dev/null 2>&1; then
        runuser -u munge -- /usr/sbin/munged --force
        touch "$DIR/munged.started"  # ours to stop at `down` (one already running is left alone)
    fi
    for _ in $(seq 50); do munge -n >/dev/null 2>&1 && return; sleep 0.1; done
    fail "munged did not start (see /var/log/munge/munged.log)"
}

write_conf() {
    local cpus mem
    cpus=$(nproc)
    mem=$(( $(awk '/MemTotal/ {print int($2 / 1024)}' /proc/meminfo) - 1024 ))
    mkdir -p "$DIR/state" "$DIR/spool" "$DIR/log"
    cat > "$DIR/slurm.conf" <<EOF
ClusterName=nrbench
SlurmctldHost=$HOST
AuthType=auth/munge
CryptoType=crypto/munge
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SlurmUser=root
SlurmdUser=root
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd.log
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
ReturnToService=2
MpiDefault=none
# A requeued or cancelled job gets SIGTERM, then SIGKILL this many seconds later (SLURM's default: 30).
KillWait=10
JobRequeue=1
# A requeued job may start again this many seconds after it ended (SLURM's default: 120).
AuthInfo=cred_expire=10
NodeName=$HOST CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=debug Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF
}

start_slurm() {
    export SLURM_CONF=$DIR/slurm.conf
    /usr/sbin/slurmctld -f "$SLURM_CONF"
    /usr/sbin/slurmd -f "$SLURM_CONF"
    for _ in $(seq 100); do
        if sinfo -h -o %T 2>/dev/null | grep -q idle; then return; fi
        sleep 0.2
    done
    fail "the node did not come up idle (sinfo: $(sinfo -h -o '%T %E' 2>&1 | head -1)); see $DIR/log"
}

start_mlflow() {
    [ -x "$MLFLOW" ] || fail "$MLFLOW not found; run bash scripts/setup.sh first (or set NRBENCH_MLFLOW)"
    nohup "$MLFLOW" server --host 127.0.0.1 --port "$PORT" \
        --backend-store-uri "sqlite:///$DIR/mlflow.db" --default-artifact-root "$DIR/mlartifacts" \
        >"$DIR/log/mlflow.log" 2>&1 &
    echo $! > "$DIR/mlflow.pid"
    for _ in $(seq 150); do
        if curl -sf "http://127.0.0.1:$PORT/health" >/dev/null 2>&1; then return; fi
        sleep 0.2
    done
    fail "mlflow server did not answer on port $PORT; see $DIR/log/mlflow.log"
}

kill_pidfile() {
    local file=$1
    [ -f "$file" ] || return 0
    local pid
    pid=$(cat "$file")
    if kill "$pid" 2>/dev/null; then
        for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
        kill -9 "$pid" 2>/dev/null || true
    fi
    rm -f "$file"
}

up() {
    mkdir -p "$DIR/log"
    install_missing
    start_munge
    write_conf
    start_slurm
    start_mlflow
    cat > "$DIR/cluster.env" <<EOF
export SLURM_CONF=$DIR/slurm.conf
export MLFLOW_TRACKING_URI=http://127.0.0.1:$PORT
EOF
    echo "cluster: node $HOST ($(nproc) CPUs), partition debug, MLflow at http://127.0.0.1:$PORT"
    echo "$DIR/cluster.env"
}

down() {
    if [ -f "$DIR/slurm.conf" ]; then
        SLURM_CONF=$DIR/slurm.conf scancel --user=root 2>/dev/null || true
    fi
    kill_pidfile "$DIR/mlflow.pid"
    kill_pidfile "$DIR/slurmd.pid"
    kill_pidfile "$DIR/slurmctld.pid"
    if [ -f "$DIR/munged.started" ] && [ -f /run/munge/munged.pid ]; then
        kill_pidfile /run/munge/munged.pid
        rm -f "$DIR/munged.started"
    fi
    echo "cluster: stopped (state kept in $DIR)"
}

status() {
    local any=1
    for name in slurmctld slurmd mlflow; do
        if [ -f "$DIR/$name.pid" ] && kill -0 "$(cat "$DIR/$name.pid")" 2>/dev/null; then
            echo "$name: running (pid $(cat "$DIR/$name.pid"))"; any=0
        else
            echo "$name: not running"
        fi
    done
    return $any
}

case "${1:-}" in
    up) up ;;
    down) down ;;
    status) status ;;
    *) echo "usage: bash scripts/cluster.sh up|down|status" >&2; exit 2 ;;
esac
