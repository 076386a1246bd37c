#!/usr/bin/env bash
# GPU measurements of issue 31 on a lent CUDA machine, unattended, run from the repository root
# with the machine's own python3 (PyTorch, onnx, onnxruntime CPU, OpenCV, numpy; no
# onnxruntime-gpu and no network: onnxruntime-gpu travels in pieces).
#
#   benchmarks/gpu_check.sh part      keep the onnxruntime-gpu piece in .ortpart/ (one per call)
#   benchmarks/gpu_check.sh measure   the last piece: unpack onnxruntime-gpu, then every table
#   benchmarks/gpu_check.sh dry       the same steps on this CPU at tiny sizes (no GPU, no pieces):
#                                     checks the script and the benchmarks' arguments
#
# benchmarks/gpu_pieces.sh makes what travels (run it here first, with network access): the
# OpenEXR wheel in .whl/, onnxruntime-gpu (tools, transformers, quantization and the TensorRT
# provider removed) as one xz tar in pieces of 38.9 MB in .ortpieces/, and the graph before issue 31
# in .ortpieces/before/ (the "before" rows). A call carries at most 64 MiB: each `part` call
# carries one piece (copy it to .ortpart/ and name .ortpart in the run's carry), the `measure`
# call the last piece and .ortpieces/before.
#
# Device-time plan (10 minutes in all): the machine's start (about 35-60 s), one `part` call per
# piece but the last (a few seconds each plus the transfer), then `measure` (its steps below run
# against one deadline, MEASURE_S = 540 s by default, each cut short to what is left, so the
# call ends inside the tool's 600 s and the tables come back). Results go to $OUT (*.md, *.log).
#
# What `measure` measures, in order of importance:
#  0. the device route (issue 31 item 3-4: the frame kept on the GPU from the raw mosaic to the
#     Mueller image, bench_device_route.py): per step (upload, pre, statistics, networks, post,
#     copy-back) for the full colour and mono sensor, superpixel and full resolution, CUDA and
#     the machine's CPU; the device route's CUDA-vs-CPU parity; the live grid with the probe on
#     every frame and every 8th (its error against the hidden truth);
#  1. the networks' step of one full colour sensor frame (612x512: probe + frame pass) on CUDA,
#     before (the Acos graph on one dynamic session) and after (fixed-size sessions, the frame
#     and probe graphs, HEURISTIC, TF32 off, CUDA graphs where accepted), with the CUDA-vs-CPU
#     parity of the after path and the refusals onnxruntime printed (bench_sessions.py); the same
#     with one frame pass (the training axis);
#  2. the whole single-shot path per case on CUDA (bench_single_shot.py: issue 22/31's targets:
#     512x512 full resolution, full sensor colour superpixel and full resolution, mono, binning);
#  3. the live Mueller view on CUDA and CPU (bench_live_mueller.py);
#  4. one network pass per provider setting with onnxruntime's profile (bench_network_pass.py);
#  5. the CPU rows of 2 on the machine's 16 cores, for the comparison.
#
# STEPS="name ..." runs only the named steps (the logs' names; default all): the dry mode's test
# runs the device route's alone. EXTRA="script.py args" runs one more script first (step "extra").
set -u
# polrig is not installed on a lent machine: links name its folders as an install does
# (benchmarks/polrig_path.sh), first on PYTHONPATH; the checkout after them (the benchmarks
# package). PYTHONSAFEPATH: no `python -c` or child puts the working folder (the root, whose
# polrig/ lacks polrig.models) first on sys.path.
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT  # the links, whichever way the script ends
. benchmarks/polrig_path.sh "$work"
export PYTHONPATH="$PYTHONPATH:$PWD" PYTHONSAFEPATH=1 PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/gpu-out}
PY=${PY:-python3}
MEASURE_S=${MEASURE_S:-540}
mkdir -p "$OUT"
T0=$(date +%s)

# run NAME CAP_S CMD...: CMD with at most CAP_S seconds and never past the deadline; its output in
# $OUT/NAME.log, the tail printed when it fails
run() {
    local name=$1 cap=$2; shift 2
    if [ -n "${STEPS:-}" ] && [[ " $STEPS " != *" $name "* ]]; then return; fi
    local left=$(( MEASURE_S - ($(date +%s) - T0) ))
    (( left < cap )) && cap=$left
    if (( cap < 10 )); then echo "SKIPPED $name (deadline)"; return; fi
    local t=$(date +%s)
    timeout "$cap" "$@" > "$OUT/$name.log" 2>&1
    local rc=$?
    echo "$name: rc $rc, $(( $(date +%s) - t )) s (cap $cap s)"
    (( rc != 0 )) && tail -15 "$OUT/$name.log"
    return 0
}

before_args() {  # the graph before issue 31, where it travelled
    if [ -f .ortpieces/before/single_shot.onnx ]; then echo "--before .ortpieces/before"; fi
}

case "${1:-}" in
part)
    mkdir -p /root/ortparts && cp .ortpart/* /root/ortparts/ && ls -la /root/ortparts
    ;;
measure)
    # CUDA/cuDNN of the image's NVIDIA pip packages on the loader's path (onnxruntime-gpu looks
    # there; preload_dlls only searches beside its own folder)
    NV=$($PY -c "import glob, os, site; print(':'.join(sorted({os.path.dirname(p) for d in site.getsitepackages() for p in glob.glob(d + '/nvidia/*/lib/*.so*')})))" 2>/dev/null)
    export LD_LIBRARY_PATH="${NV}${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    if compgen -G ".whl/*.whl" > /dev/null; then
        $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/wheels .whl/*.whl
    fi
    mkdir -p /root/ortparts /tmp/site
    [ -d .ortpart ] && cp .ortpart/* /root/ortparts/
    cat /root/ortparts/ort.tar.xz.* | xz -d -T0 | tar xf - -C /tmp/site || { echo "UNPACK FAILED"; ls -la /root/ortparts; }
    # onnxruntime-gpu must shadow the image's CPU onnxruntime: /tmp/site first
    export PYTHONPATH="/tmp/site:$PYTHONPATH:/tmp/wheels"
    echo "unpacked in $(( $(date +%s) - T0 )) s"
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
    $PY -c "import onnxruntime as o; print('onnxruntime', o.__version__, o.get_available_providers())"
    $PY -c "from polrig.models import devices; print('gpus', devices.cuda_device_count(), 'auto ->', devices.choose_providers('auto', __import__('onnxruntime').get_available_providers()))"
    # EXTRA="script.py args": one more script first, in the same environment (a one-off check)
    [ -n "${EXTRA:-}" ] && run extra 150 $PY $EXTRA
    run device_route 150 $PY benchmarks/bench_device_route.py --devices cuda,cpu --sizes 2448x2048 --rounds 3 --live-frames 8 --out "$OUT/device_route.md"
    run sessions_cuda 100 $PY benchmarks/bench_sessions.py --device cuda $(before_args) --size 612x512 --rounds 20 --out "$OUT/sessions_cuda.md"
    run single_shot_cuda 120 $PY benchmarks/bench_single_shot.py --device cuda --cases 0,3,4,6,7 --rounds 3 --out "$OUT/single_shot_cuda.md"
    run live_mueller 50 $PY benchmarks/bench_live_mueller.py --frames 10 --devices cuda,cpu --out "$OUT/live_mueller.md"
    run sessions_cuda_frame 40 $PY benchmarks/bench_sessions.py --device cuda $(before_args) --size 612x512 --rounds 20 --training-axis --out "$OUT/sessions_cuda_frame.md"
    run network_pass 40 $PY benchmarks/bench_network_pass.py --devices cuda,cpu --rounds 5 --no-torch --profile --out "$OUT/network_pass.md"
    run single_shot_cpu 50 $PY benchmarks/bench_single_shot.py --device cpu --cases 3,4 --rounds 2 --out "$OUT/single_shot_cpu16.md"
    cat "$OUT"/*.md 2>/dev/null
    grep -h "^polrig: " "$OUT"/*.log 2>/dev/null | sort | uniq -c   # refusals onnxruntime gave
    echo "measure: $(( $(date +%s) - T0 )) s"
    ;;
dry)
    run device_route 120 $PY benchmarks/bench_device_route.py --devices cpu --sizes 64x64 --rounds 1 --live-frames 2 --out "$OUT/device_route.md"
    run sessions_cpu 120 $PY benchmarks/bench_sessions.py --device cpu $(before_args) --size 64x64 --rounds 2 --out "$OUT/sessions_cpu.md"
    run sessions_cpu_frame 60 $PY benchmarks/bench_sessions.py --device cpu --size 64x64 --rounds 2 --training-axis --out "$OUT/sessions_cpu_frame.md"
    run network_pass 120 $PY benchmarks/bench_network_pass.py --devices cpu --size 64x64 --rounds 2 --no-torch --out "$OUT/network_pass.md"
    cat "$OUT"/*.md 2>/dev/null
    echo "dry: $(( $(date +%s) - T0 )) s"
    ;;
*)
    echo "usage: $0 part | measure | dry" >&2; exit 2
    ;;
esac
