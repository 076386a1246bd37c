#!/usr/bin/env bash
# One GPU lease for both device jobs, overlapped: the training of benchmarks/gpu_train.sh runs
# while the onnxruntime-gpu pieces of benchmarks/gpu_check.sh travel, then the measurements run on
# the idle GPU. Run from the repository root of a lent machine, one verb per device call:
#
#   benchmarks/gpu_lease.sh start BUDGET_MIN [SIZE]   carry .ortpart (piece 0) and .whl: keep the
#                      piece, copy the checkout to /root/lease-repo and start gpu_train.sh there in
#                      its own process session (it outlives the call; the machine stays held while
#                      calls follow within its idle release)
#   benchmarks/gpu_check.sh part                      carry .ortpart (pieces 1 .. n-2)
#   benchmarks/gpu_lease.sh finish DEADLINE_S         carry .ortpart (the last piece),
#                      .ortpieces/before and .whl: wait for the training, bring back its five
#                      files, then gpu_check.sh measure with what is left of DEADLINE_S seconds
#                      (counted from this call's start), its tables and logs as one measure.tar.gz
#
# The copy in /root/lease-repo keeps the training's files fixed while later calls refresh the
# checkout. Eight files at most come back from a call: the training's five and measure.tar.gz.
set -u
OUT=${OUT:-/tmp/gpu-out}
T0=$(date +%s)
case "${1:-}" in
start)
    budget=${2:?budget in minutes}; size=${3:-large}
    mkdir -p /root/ortparts && cp .ortpart/* /root/ortparts/
    rm -rf /root/lease-repo /root/train-out && cp -a . /root/lease-repo
    cd /root/lease-repo
    setsid nohup env OUT=/root/train-out bash benchmarks/gpu_train.sh "$budget" "$size" \
        > /root/train.log 2>&1 < /dev/null &
    echo $! > /root/train.pid
    sleep 20
    nvidia-smi --query-gpu=name,driver_version,memory.total,memory.used,utilization.gpu --format=csv,noheader
    tail -5 /root/train.log
    ;;
finish)
    deadline=${2:?seconds for this call}
    mkdir -p /root/ortparts "$OUT" && cp .ortpart/* /root/ortparts/
    pid=$(cat /root/train.pid 2>/dev/null || echo 0)
    while kill -0 "$pid" 2>/dev/null && (( $(date +%s) - T0 < deadline - 120 )); do sleep 2; done
    kill -0 "$pid" 2>/dev/null && { echo "training still running at $(( $(date +%s) - T0 )) s: stopped"; kill -- -"$pid"; sleep 2; }
    echo "training ended after $(( $(date +%s) - T0 )) s of this call"
    cp /root/train-out/* "$OUT"/ 2>/dev/null
    grep -E "^(lease|probe|data|training|ship)|epoch.*(  0|lr 5.00e-05)" /root/train.log | tail -30
    left=$(( deadline - ($(date +%s) - T0) - 25 ))
    mkdir -p /root/measure
    OUT=/root/measure MEASURE_S=$left bash benchmarks/gpu_check.sh measure
    tar czf "$OUT/measure.tar.gz" -C /root/measure .
    ls -la "$OUT"
    ;;
*)
    echo "usage: $0 start BUDGET_MIN [SIZE] | finish DEADLINE_S" >&2; exit 2
    ;;
esac
