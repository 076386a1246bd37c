#!/usr/bin/env bash
# How the sessions in this folder were made (kept as the record of their provenance; see README.md).
#
# They were written by polrig at commit 45517b4 (main before the layered package, session
# schema version 1) on its simulated rig, with OUT=/tmp/legacy (the path their manifests'
# command lines name). Running this again makes equivalent sessions: the same raw frames and
# results (the simulator is seeded; its noise is keyed by pose, state and repeat), new times.
#
# Usage: make.sh OUT [OLD_CHECKOUT] [PYTHON]
#   OUT           folder the sessions and rig files are written to
#   OLD_CHECKOUT  a checkout of commit 45517b4 (default /tmp/oldmain; make one with
#                 `git worktree add --detach /tmp/oldmain 45517b4` in this repository)
#   PYTHON        a Python with polrig's dependencies installed (default python3); the old
#                 checkout is put first on PYTHONPATH, so its `polrig` (top-level `models`,
#                 `sim`, ... packages of that time) is the one that runs
#
# Then, for the tests: copy OUT/{reference,single-shot,interrupted} and OUT/rig-*.toml here and
# delete each session's session.lock (the last writer's pid; not session data).
set -euo pipefail
OUT=$(realpath -m "$1")
OLD=${2:-/tmp/oldmain}
PYTHON=${3:-python3}
mkdir -p "$OUT"
cd "$OLD"
test "$(git rev-parse --short=7 HEAD)" = 45517b4 || { echo "$OLD is not a checkout of 45517b4" >&2; exit 2; }
PY="env PYTHONPATH=$OLD $PYTHON -m polrig.cli"
cfg() { printf '[sim]\nsize = "64x64"\nsensor = "imx250mzr"\nclock_speed = %s\nseed = 11\nscene = "box"\nnoise = true\n' "$2" > "$1"; }
cfg "$OUT/rig-fast.toml" inf   # the simulated clock as fast as the host
cfg "$OUT/rig-slow.toml" 1.0   # real-time motion: a capture takes seconds, time to interrupt it
rm -rf "$OUT/reference" "$OUT/single-shot" "$OUT/interrupted"
$PY capture --poses 0,90 --mode reference --config "$OUT/rig-fast.toml" --out "$OUT/reference" --no-progress
$PY capture --poses 0 --mode single-shot --config "$OUT/rig-fast.toml" --out "$OUT/single-shot" --no-progress
# interrupted after the first capture is complete (SIGTERM, handled as Ctrl-C, while the
# second pose is acquired): capture 0 complete, captures 1 and 2 pending
$PY capture --poses 0,120,240 --mode reference --config "$OUT/rig-slow.toml" --out "$OUT/interrupted" --no-progress &
pid=$!
for i in $(seq 600); do
  if [ -f "$OUT/interrupted/session.json" ] && grep -q '"status": "complete"' "$OUT/interrupted/session.json"; then break; fi
  sleep 0.1
done
kill -TERM $pid; wait $pid || echo "exit $?"
