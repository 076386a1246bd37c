#!/usr/bin/env bash
# The GPU training lease of issue 32 (items 2, 5, 6): one unattended call on a lent CUDA machine,
# run from the repository root with the machine's own python3 (PyTorch, onnx, onnxruntime CPU).
#
#   benchmarks/gpu_train.sh [BUDGET_MIN [SIZE]]     default 7.5 large
#
# It runs python -m polrig.models.lease (models/lease.py: held-out sets made on the CPU cores while
# the GPU trains on scenes it makes itself, PIPNet, PMMNet and the direct baseline in one budget with
# bf16 autocast, export and ONNX check, evaluation against the shipped weights of the same size, the
# shipping rule, the sigma refitted where it ships), continuing the size's committed checkpoint
# (models/weights[/large]/checkpoint.pt) where there is one. The device tool brings back at most 8
# files of 16 MiB, so $OUT gets five:
#   weights.tar      the new graphs, model.json (size, hardware, lineage), uncertainty.json if refitted
#   checkpoint.pt    the committed form of the run's checkpoint (Adam's moments in bf16 if needed)
#   tables.tar.gz    eval_<set>_<new|baseline>.md/.json, log.csv, summary.json
#   run.json         hardware, budget, phases, plan, scores, verdict
#   lease.log        the run's output
# Shipping (only where run.json says "ship": true): python -m polrig.models.lease --ship FOLDER (the
# five files fetched here) copies the weights and checkpoint.pt into models/weights/large/ (or
# models/weights/ for small) and the new weights' tables into benchmarks/results/; commit them with
# run.json's numbers.
#
# Limits (the device tool): 10 minutes per command, 15 minutes of device time per session with
# the machine's start (about a minute): a budget of 7.5 minutes leaves the start, the wheels'
# install and a margin. The lease itself ends within its budget less 2 % (models/lease.py).
# LEASE_DRY=1: the same at tiny scale on the CPU in seconds (tests/test_models_lease.py runs it).
set -u -o pipefail
export PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE
OUT=${OUT:-/tmp/gpu-out}
PY=${PY:-python3}
budget=${1:-7.5}
size=${2:-large}
mkdir -p "$OUT" && OUT=$(cd "$OUT" && pwd)  # absolute: the lease runs from another folder
# wheels the image lacks (OpenEXR for cp312) travel in .whl/ (benchmarks/gpu_pieces.sh)
if compgen -G ".whl/*.whl" > /dev/null && [ ! -d /tmp/wheels ]; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/wheels .whl/*.whl
fi
export PYTHONPATH="${PYTHONPATH:+$PYTHONPATH:}/tmp/wheels"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT  # the links and the run's folder, whichever way the script ends
# polrig is not installed on a lent machine: links name its folders as an install does
. benchmarks/polrig_path.sh "$work"
dry=()
if [ "${LEASE_DRY:-0}" = 1 ]; then
    dry=(--dry --sets "${LEASE_SETS:-unseen_shapes,mm_conductor,calibration}")
else
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || true
fi
limit=$(awk -v b="$budget" 'BEGIN { printf "%d", b * 60 + 60 }')
repo=$PWD
cd "$work"  # not the repository root: its polrig/ would come first on sys.path (polrig_path.sh)
$PY -c "import polrig.models.lease as m; print('polrig.models from', m.__file__)" || { echo "polrig does not import here"; exit 1; }
timeout "$limit" $PY -m polrig.models.lease --out "$work/lease" --budget-min "$budget" --model-size "$size" \
    "${dry[@]}" 2>&1 | tee "$OUT/lease.log"
rc=$?
cd "$repo"
if [ -d "$work/lease" ]; then
    l="$work/lease"
    [ -d "$l/weights" ] && tar cf "$OUT/weights.tar" -C "$l" weights
    [ -f "$l/checkpoint.pt" ] && cp "$l/checkpoint.pt" "$OUT/"
    [ -f "$l/run.json" ] && cp "$l/run.json" "$OUT/"
    (cd "$l" && tar czf "$OUT/tables.tar.gz" --ignore-failed-read $(ls eval_* log.csv summary.json sigma_fit.log 2>/dev/null))
fi
rm -rf "$work"
ls -la "$OUT"
exit $rc
