"""``benchmarks/gpu_check.sh dry`` (its CPU mode at tiny sizes) runs the device route's benchmark
as a lent GPU's ``measure`` would, and brings its table back: the script and the benchmark's
arguments are known to work before a lease spends minutes on them."""

import os
import pathlib
import subprocess
import sys

import pytest

from polrig.models.runtime import WEIGHTS_DIR

pytestmark = pytest.mark.skipif(not (WEIGHTS_DIR / "single_shot.onnx").is_file(), reason="no shipped graph")
REPO = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_gpu_checks_dry_mode_brings_back_the_device_route_table(tmp_path):
    """Run as on a lent machine, where polrig is not installed: an interpreter without site
    processing (the editable install's finder is not loaded) that sees only the dependencies;
    the script names polrig's folders itself (benchmarks/polrig_path.sh)."""
    deps = os.pathsep.join(p for p in sys.path if p.endswith("site-packages"))
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    env = dict(os.environ, OUT=str(tmp_path), STEPS="device_route", PY=f"{sys.executable} -S", PYTHONPATH=deps,
               TMPDIR=str(scratch))
    proc = subprocess.run(["bash", "benchmarks/gpu_check.sh", "dry"], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0 and "device_route: rc 0" in proc.stdout, proc.stdout[-2000:]
    # its links' folder removed (each run left one in /tmp); onnxruntime's own ".ses" file stays
    assert not [p for p in scratch.iterdir() if p.is_dir()]
    assert "sessions_cpu" not in proc.stdout  # STEPS ran the named step alone
    text = (tmp_path / "device_route.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| CPUExecutionProvider | 64x64")]
    assert len(rows) == 4  # colour and mono, superpixel and full resolution
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        host, device = float(cells[2]), float(cells[3].strip("*"))
        assert host > 0 and device > 0
        assert float(cells[-1]) < 1e-5  # the device route equals the host route
    assert "GPU: none" in text and "| 8 |" in text  # the probe every 8 frames, measured


def test_bench_single_shot_splits_the_device_routes_frame_into_its_steps(tmp_path):
    """``bench_single_shot.py`` on the device route (CUDA's): the route named, the warm frame's
    steps tabled (here the device route through the CPU provider, one small frame)."""
    import numpy as np

    from benchmarks import bench_single_shot as bench
    from polrig.app.single_shot import SingleShot
    from polrig.models.runtime import SingleShotModel

    route = SingleShot(SingleShotModel.load(device="cpu", threads=1), "device")
    src = bench.write_case_raw((128, 128), bench.COLOUR, tmp_path / "f.png", np.random.default_rng(0))
    rows = [bench.warm_once(src, [], route, tmp_path / "o.exr") for _ in range(2)]
    assert all(r["network"] > 0 for r in rows)
    raw = {"provider": route.provider, "gpu": None, "frame_route": route.frame_route, "onnxruntime": "x",
           "threads": 1, "cores": 1, "spinning": False, "rounds": 2, "warm": {"128x128 superpixel": rows},
           "cold": {"128x128 superpixel": [{"wall": 1.0, "cpu": 1.0, "peak_mb": 1.0}]}}
    text = bench.render(raw)
    assert "frame route device" in text
    steps = [line for line in text.splitlines() if line.startswith("| 128x128 superpixel | ")]
    assert len(steps) == 2 and len(steps[1].split("|")) == 9  # the case and its six steps
