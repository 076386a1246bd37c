#!/usr/bin/env bash
# Make what benchmarks/gpu_check.sh carries to a lent GPU machine (run here, from the repository
# root, with network access): the OpenEXR wheel for the machine's Python 3.12 in .whl/, and
# onnxruntime-gpu (CUDA 13 build, the machine's CUDA) unpacked, without the parts polrig does not
# use (tools, transformers, quantization, the TensorRT provider), as one xz tar split into
# pieces of 38.9 MB in .ortpieces/ (a call carries at most 64 MiB with the working tree, which is
# 22 MB now). The C API library libonnxruntime.so stays behind: the Python module links the runtime
# in itself and the CUDA provider needs only libonnxruntime_providers_shared.so (readelf -d).
# and the graph before issue 31 in .ortpieces/before/ (benchmarks/bench_sessions.py's "before").
# Each gpu_check.sh call then carries one piece: copy it into .ortpart/ first, e.g.
#   rm -rf .ortpart && mkdir .ortpart && cp .ortpieces/ort.tar.xz.0 .ortpart/
# Both folders are kept out of git by .git/info/exclude (added here if missing).
set -euo pipefail
ORT_VERSION=${ORT_VERSION:-1.31.1}
PLATFORMS=(--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64
           --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64)
for d in /.whl/ /.ortpart/ /.ortpieces/; do
    grep -qxF "$d" .git/info/exclude || echo "$d" >> .git/info/exclude
done
mkdir -p .whl .ortpieces
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    "${PLATFORMS[@]}" -d .whl OpenEXR
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    "${PLATFORMS[@]}" -d "$tmp" "onnxruntime-gpu==$ORT_VERSION"
mkdir "$tmp/ort"
(cd "$tmp/ort" && python3 -m zipfile -e "$tmp"/onnxruntime_gpu-*.whl . \
    && rm -rf onnxruntime/transformers onnxruntime/tools onnxruntime/quantization \
              onnxruntime/capi/libonnxruntime_providers_tensorrt.so onnxruntime/capi/libonnxruntime.so.* \
         && sed -i '/libonnxruntime\.so\./d' onnxruntime_gpu-*.dist-info/RECORD)
rm -f .ortpieces/ort.tar.xz.*
(cd "$tmp/ort" && tar cf - . | xz -T0 -9) | split -b 38900000 -d -a 1 - .ortpieces/ort.tar.xz.
# the single-shot graph before issue 31 (with Acos), for bench_sessions.py's "before" rows
mkdir -p .ortpieces/before
git show 5cfac96:models/weights/single_shot.onnx > .ortpieces/before/single_shot.onnx
git show 5cfac96:models/weights/model.json > .ortpieces/before/model.json
ls -l .whl .ortpieces .ortpieces/before
