"""``python -m benchmarks open_scale``: a tiny run writes its table, the factor finds the prior's
error along the open direction, and below the sample's size the sampled factor is every band's."""


def test_a_tiny_run_writes_the_table(tmp_path, monkeypatch):
    from benchmarks import bench_open_scale

    monkeypatch.setattr(bench_open_scale, "SIZE", (96, 128))  # the full sensor is the benchmark's, not the suite's
    out = tmp_path / "o.md"
    assert bench_open_scale.main(["--rounds", "1", "--out", str(out)]) == 0
    rows = [line.split(" | ") for line in out.read_text().splitlines() if line.startswith("| imx250")]
    assert [r[0] for r in rows] == ["| imx250mzr", "| imx250myr"] and all(len(r) == 11 for r in rows)
    for r in rows:
        assert r[3:5] == r[6:8] and int(r[4]) > 100  # all bands sampled at this size
        raw = float(r[3].split("(")[1].rstrip(")"))
        assert 1.2 < raw < 2.2  # the prior errs by 1.5 sigma along the open direction
