"""The GPU diagnostic benchmark runs where CI can run it (the CPU rows, tiny size), so it is
known to work before a GPU lease spends minutes on it (benchmarks/gpu_check.sh)."""

import pytest

from polrig.models.runtime import WEIGHTS_DIR

pytestmark = pytest.mark.skipif(not (WEIGHTS_DIR / "single_shot.onnx").is_file(), reason="no shipped graph")


def test_cpu_rows_onnxruntime_and_pytorch_and_the_profile(tmp_path, capsys):
    pytest.importorskip("torch")
    from benchmarks.bench_network_pass import main

    out = tmp_path / "pass.md"
    assert main(["--size", "64x48", "--rounds", "2", "--devices", "cpu", "--threads", "1", "--profile",
                 "--out", str(out)]) == 0
    text = out.read_text()
    assert "| onnxruntime | cpu |" in text and "| pytorch | cpu |" in text
    from benchmarks.bench_single_shot import gpu_name

    assert ("GPU: none" in text) == (gpu_name() is None)  # the table says which GPU, if any
    rows = [line for line in text.splitlines() if line.startswith("| onnxruntime | cpu")]
    first, frame = (float(v) for v in rows[0].split("|")[4:6])
    assert first > 0 and frame > 0
    assert "| Conv |" in text or "| FusedConv |" in text  # the profile lists the convolutions


def test_a_device_that_does_not_start_is_a_row_not_a_crash(tmp_path):
    """On a machine without CUDA, asking for it gives error rows (what failed), not a traceback."""
    import onnxruntime as ort

    if "CUDAExecutionProvider" in ort.get_available_providers():
        pytest.skip("this machine has the CUDA provider")
    from benchmarks.bench_network_pass import main

    out = tmp_path / "pass.md"
    assert main(["--size", "32x32", "--rounds", "1", "--devices", "cuda", "--out", str(out)]) == 0
    rows = [line for line in out.read_text().splitlines() if "| cuda |" in line]
    assert len(rows) == 4  # three cuDNN searches and PyTorch
    assert all(len(r.split("|")[4].strip()) > 3 for r in rows)  # each says what failed
