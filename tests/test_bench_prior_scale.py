"""``python -m benchmarks prior_scale``: a tiny run writes its table, and below the sample's
size the sampled scale is the whole image's."""


def test_a_tiny_run_writes_the_table(tmp_path, monkeypatch):
    from benchmarks import bench_prior_scale

    monkeypatch.setattr(bench_prior_scale, "SIZE", (64, 96))  # the full sensor is the benchmark's, not the suite's
    out = tmp_path / "p.md"
    assert bench_prior_scale.main(["--rounds", "1", "--out", str(out)]) == 0
    rows = [line.split(" | ") for line in out.read_text().splitlines() if line.startswith("| imx250")]
    assert all(len(r) == 12 for r in rows)  # with the peak memory column
    assert [r[0] for r in rows] == ["| imx250mzr"] * 4 + ["| imx250myr"] * 4
    assert [r[2] for r in rows] == ["whole frame", "15 % of it"] * 4
    for r in rows:  # all bands sampled at this size: the same factor and innovations
        assert r[4:6] == r[7:9] and int(r[5]) > 0
    for whole, part in zip(rows[::2], rows[1::2]):  # the object's share of the innovations, about
        assert 0.1 < int(part[5]) / int(whole[5]) < 0.2
