#!/usr/bin/env bash
# GPU training and measurements of issue 22 (items 3 and 4) on a lent CUDA machine, run from the
# repository root with the machine's own python3 (PyTorch, onnx, onnxruntime CPU, OpenCV, numpy).
# (This was benchmarks/gpu_check.sh until issue 31, whose measurements took that name.)
#
#   benchmarks/gpu_train.sh start BUDGET_MIN   probe the machine, a tiny CUDA training run end to
#                                              end, then the paper-scale run in the background
#   benchmarks/gpu_train.sh part               keep the onnxruntime-gpu archive piece in .ortpart/
#   benchmarks/gpu_train.sh wait               until the background training has ended
#   benchmarks/gpu_train.sh finish             unpack onnxruntime-gpu, wait for the training, time
#                                              one network pass per setting (bench_network_pass),
#                                              single-shot and the live Mueller view on CUDA and
#                                              CPU, pack the results
#
# benchmarks/gpu_pieces.sh makes what travels (run it here first, with network access).
# Wheels the image lacks travel in .whl/ (OpenEXR for cp312); onnxruntime-gpu (the wheel
# unpacked, without its tools/transformers/quantization folders and the TensorRT provider, as
# one xz tar of 200 MB) travels in four pieces of 50.8 MB (`split -b 50800000 -d -a 1`), one per
# call in .ortpart/, into /root/ortparts: a call carries at most 64 MiB. Results go to $OUT
# (paper-scale.tar.gz, results.tar.gz, the tables).
#
# As run on 2026-11-26 (NVIDIA H200, 15 minutes of device time): `start 7.5` (58 s, the machine
# already started: its start took about 35 s), three `part` calls (a few seconds each; the last
# followed by `wait`: 418 s), then `finish` (311 s; 3 rounds with --anatomy on CUDA, 10 live
# frames per row, 2 CPU rounds): 866 s in all. A call may run 600 s at most, so `wait` must be
# its own call; a machine left idle for 30 s is given back and everything on it is lost.
set -u
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/gpu-out}
mkdir -p "$OUT" /root/ortparts
PY=${PY:-python3}
# CUDA/cuDNN of the image's NVIDIA pip packages on the loader's path (onnxruntime-gpu looks
# there; preload_dlls only searches beside its own folder).
NV=$($PY -c "import glob, os, site; print(':'.join(sorted({os.path.dirname(p) for d in site.getsitepackages() for p in glob.glob(d + '/nvidia/*/lib/*.so*')})))" 2>/dev/null)
export LD_LIBRARY_PATH="${NV}${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"

# OpenEXR (and any other wheel in .whl/) in its own folder, for every phase
if compgen -G ".whl/*.whl" > /dev/null && [ ! -d /tmp/wheels ]; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/wheels .whl/*.whl
fi
export PYTHONPATH="$PYTHONPATH:/tmp/wheels"

case "${1:-}" in
start)
    budget=${2:-7.5}
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
    nproc; free -g | head -2
    $PY -c "import sys, torch, numpy, onnxruntime, onnx, cv2; print(sys.version.split()[0], 'torch', torch.__version__, torch.cuda.is_available(), 'numpy', numpy.__version__, 'ort', onnxruntime.__version__, 'onnx', onnx.__version__, 'cv2', cv2.__version__)"
    [ -d .ortpart ] && cp .ortpart/* /root/ortparts/
    t0=$(date +%s)
    rm -rf /tmp/smoke /tmp/paper
    if ! $PY -m polrig.models.paper_scale --out /tmp/smoke --budget-min 1 --size 32 --width 8 --train-samples 8 \
            --holdout-samples 2 --epochs 1 --jobs 4 > "$OUT/smoke.log" 2>&1; then
        echo "SMOKE FAILED"; tail -30 "$OUT/smoke.log"; exit 1
    fi
    tail -3 "$OUT/smoke.log"; grep -o '"training_device": "[a-z]*"' /tmp/smoke/run.json
    echo "smoke $(( $(date +%s) - t0 )) s"
    setsid nohup $PY -m polrig.models.paper_scale --out /tmp/paper --budget-min "$budget" --size 256 \
        --work /tmp > /tmp/paper.log 2>&1 < /dev/null &
    echo $! > /tmp/paper.pid
    sleep 20; cat /tmp/paper.log
    ;;
part)
    cp .ortpart/* /root/ortparts/ && ls -la /root/ortparts
    tail -5 /tmp/paper.log
    ;;
wait)
    while kill -0 "$(cat /tmp/paper.pid)" 2> /dev/null; do sleep 3; done
    cat /tmp/paper.log
    ;;
finish)
    cp .ortpart/* /root/ortparts/ 2>/dev/null
    mkdir -p /tmp/site
    cat /root/ortparts/ort.tar.xz.* | $PY -c "import lzma, sys, tarfile; tarfile.open(fileobj=lzma.open(sys.stdin.buffer), mode='r|').extractall('/tmp/site')" \
        || { echo "UNPACK FAILED"; ls -la /root/ortparts; }
    # onnxruntime-gpu must shadow the image's CPU onnxruntime: /tmp/site before site-packages
    export PYTHONPATH="/tmp/site:$PYTHONPATH"
    $PY -c "import onnxruntime as o; print('onnxruntime', o.__version__, o.get_available_providers())"
    while kill -0 "$(cat /tmp/paper.pid)" 2> /dev/null; do sleep 5; done
    cat /tmp/paper.log | tail -20
    [ -d /tmp/paper ] && tar czf "$OUT/paper-scale.tar.gz" -C /tmp paper paper.log
    R=/tmp/results; mkdir -p $R
    # first the one-pass diagnosis (about a minute): cuDNN searches, shape alternation, copies,
    # PyTorch on the same GPU (benchmarks/bench_network_pass.py)
    $PY benchmarks/bench_network_pass.py --devices cuda,cpu --rounds 10 --profile --out $R/network_pass.md \
        > $R/network_pass.log 2>&1 || tail -20 $R/network_pass.log
    $PY benchmarks/bench_single_shot.py --device cuda --cases 0,3,4,6,7 --rounds 3 --anatomy \
        --out $R/single_shot_cuda.md > $R/bench_cuda.log 2>&1 || tail -20 $R/bench_cuda.log
    $PY benchmarks/bench_live_mueller.py --frames 10 --devices cuda,cpu --out $R/live_mueller.md \
        > $R/live.log 2>&1 || tail -20 $R/live.log
    $PY benchmarks/bench_single_shot.py --device cpu --cases 3,4 --rounds 2 --out $R/single_shot_cpu16.md \
        > $R/bench_cpu.log 2>&1 || tail -20 $R/bench_cpu.log
    cp $R/*.md "$OUT/" 2>/dev/null
    tar czf "$OUT/results.tar.gz" -C /tmp results
    cat $R/*.md 2>/dev/null
    ls -la "$OUT"
    ;;
*)
    echo "usage: $0 start BUDGET_MIN | part | wait | finish" >&2; exit 2
    ;;
esac
