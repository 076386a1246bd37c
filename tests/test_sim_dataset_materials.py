"""Datasets with the material mixes and interreflections of issue 23 (``polrig.sim.dataset``,
``polrig sim dataset --materials MIX --indirect-samples N``, ``[sim] indirect_samples``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.cli import main
from polrig.errors import ConfigError
from polrig.optics import realizability
from polrig.sensor.noise import SensorModel
from polrig.sim import create_sim_rig
from polrig.sim.dataset import (
    effective_eta,
    generate_dataset,
    load_shard,
    make_sample,
    material_kind,
    shard_name,
)
from polrig.sim.materials import (
    MATERIAL_KINDS,
    MATERIAL_MIXES,
    random_material,
    random_surface_material,
)
from polrig.sim.options import parse_options
from polrig.sim.world import ideal_analyzer_images

SIZE = dict(width=24, height=24)
#: Arrays that depend only on the sample's geometry, light, pose and polarizer state.
GEOMETRY = ("mask", "normal", "wi", "wo", "s_in", "family", "index", "stage_deg", "lit", "stage_zero_axis")


def _same(a: dict, b: dict, keys) -> bool:
    return all(np.array_equal(np.asarray(a[k]), np.asarray(b[k])) for k in keys)


def test_baek_draws_of_a_mix_are_the_default_samples_bit_for_bit():
    """The material stream is separate: a sample of the ``train`` mix that drew the Baek kind is
    the default sample exactly (every array), so the default datasets are as before, and the
    others share the default sample's geometry."""
    seen = set()
    for i in range(12):
        base = make_sample(i, seed=4, **SIZE)
        assert int(base["material_kind"]) == 0
        mixed = make_sample(i, seed=4, material_mix="train", **SIZE)
        kind = MATERIAL_KINDS[int(mixed["material_kind"])]
        seen.add(kind)
        assert _same(base, mixed, GEOMETRY)
        if kind == "baek":
            assert _same(base, mixed, base.keys())
        else:
            assert not np.array_equal(base["mueller"], mixed["mueller"])
    assert "baek" in seen and len(seen) > 1  # both cases ran


@pytest.mark.parametrize("mix", [m for m in MATERIAL_MIXES if m not in ("baek", "train")])
def test_mixed_samples_are_deterministic_realizable_and_self_consistent(mix):
    """Every kind: the same sample twice; its kind recorded; the truth's lit 3x3 blocks complete
    to physical (Givens-Kostinski) matrices; the analyzer images are the noisy forward model of
    the truth in the same units (standardised residuals mean ~0, std ~1)."""
    for i in range(3):
        s = make_sample(i, seed=9, holdout=True, width=32, height=32, material_mix=mix)
        again = make_sample(i, seed=9, holdout=True, width=32, height=32, material_mix=mix)
        assert _same(s, again, s.keys())
        assert MATERIAL_KINDS[int(s["material_kind"])] in MATERIAL_MIXES[mix]
        lit = s["lit"] > 0
        if not lit.any():
            continue
        blocks = np.moveaxis(s["mueller"], (-2, -1), (0, 1))[lit].reshape(-1, 3, 3).astype(np.float64)
        blocks = blocks[np.abs(blocks[:, 0, 0]) > 1e-4 * np.abs(blocks[:, 0, 0]).max()]
        completed = realizability.complete_linear(blocks)
        assert np.mean(realizability.is_physical_gk(completed)) > 0.99, mix
        clean = ideal_analyzer_images(np.einsum("cijhw,j->cihw", s["mueller"], s["s_in"]))
        model = SensorModel(full_well_e=10500.0, read_noise_e=2.3, bit_depth=12)
        use = lit & (clean.max(axis=(0, 1)) * s["scale"] < 0.9 * model.clip_dn)
        resid = (s["analyzer"] - clean)[:, :, use] * s["scale"]
        z = resid / np.sqrt(model.variance_dn2(clean[:, :, use] * s["scale"], 10000.0))
        if z.size > 200:
            assert abs(np.mean(z)) < 0.15 and 0.8 < np.std(z) < 1.2


def test_ground_truth_parameters_of_the_best_fit():
    """The image-wide parameters stored for the analytic model's best fit: a conductor's
    effective eta has its normal-incidence reflectance in green and no diffuse albedo; an
    anisotropic surface stores the geometric mean of its two roughnesses; a dispersive one its
    green index."""
    got = {}
    for i in range(40):
        for mix in ("conductor", "anisotropic", "dispersive"):
            s = make_sample(i, seed=3, material_mix=mix, **SIZE)
            if (s["mask"] > 0).any() and mix not in got:
                got[mix] = (i, s)
        if len(got) == 3:
            break
    i, s = got["conductor"]
    assert float(np.abs(s["kd"]).max()) == 0.0 and s["eta"] > 2.0
    i, s = got["anisotropic"]
    base = make_sample(i, seed=3, **SIZE)
    np.testing.assert_allclose(s["alpha"], base["alpha"], rtol=1e-5)  # sqrt(a e^u a e^-u) = a
    i, s = got["dispersive"]
    base = make_sample(i, seed=3, **SIZE)
    assert s["eta"] != base["eta"] and abs(s["eta"] - base["eta"]) < 0.02  # n(532 nm) near n_d


@settings(max_examples=50, deadline=None)
@given(st.floats(1.01, 4.0), st.floats(0.0, 8.0), st.floats(0.05, 4.0))
def test_effective_eta_matches_the_normal_incidence_reflectance(n_real, k, n_cond):
    """Closed form: a real index > 1 is its own effective index; a complex one gets the real
    index with the same R0 = |(n - 1) / (n + 1)|^2."""
    assert effective_eta(n_real) == pytest.approx(n_real, rel=1e-12)
    eta = complex(n_cond, k)
    r0 = abs((eta - 1) / (eta + 1)) ** 2
    e = effective_eta(eta)
    if r0 < 1 - 1e-9:
        assert ((e - 1) / (e + 1)) ** 2 == pytest.approx(r0, rel=1e-9, abs=1e-12)


def test_material_kind_names_each_random_kind():
    rng = np.random.default_rng(1)
    for kind in MATERIAL_KINDS[1:]:
        for _ in range(5):
            base = random_material(rng)
            assert material_kind(random_surface_material(rng, kind, base)) == kind
    assert material_kind(random_material(rng)) == "baek"


def test_interreflections_change_the_truth_and_images_together():
    """``indirect_samples``: same geometry as the direct sample, more light on concave
    terrain, deterministic, and the images remain the noisy forward model of the truth."""
    changed = 0
    for i in range(4):
        direct = make_sample(i, seed=2, holdout=True, families=["heightfield"], width=32, height=32)
        s = make_sample(i, seed=2, holdout=True, families=["heightfield"], width=32, height=32,
                        indirect_samples=4)
        assert _same(direct, s, GEOMETRY)
        assert _same(s, make_sample(i, seed=2, holdout=True, families=["heightfield"], width=32,
                                    height=32, indirect_samples=4), s.keys())
        # normalised differently (the exposure follows the brighter image): compare m00 ratios
        m = (direct["lit"] > 0) & (direct["mueller"][1, 0, 0] > 0)
        if m.sum() > 20:
            ratio = s["mueller"][1, 0, 0][m] / direct["mueller"][1, 0, 0][m]
            changed += int(np.ptp(ratio) > 1e-3)
    assert changed >= 1


def test_manifest_records_the_mix_and_transport_and_resuming_checks_them(tmp_path):
    out = tmp_path / "ds"
    generate_dataset(out, count=3, width=16, seed=1, shard_size=2, progress=False,
                     material_mix="heldout", indirect_samples=2, max_shards=1)
    man = json.loads((out / "manifest.json").read_text())
    assert man["materials"]["mix"] == "heldout" and man["materials"]["probabilities"] == MATERIAL_MIXES["heldout"]
    assert man["materials"]["kinds"] == list(MATERIAL_KINDS) and "eta" in man["materials"]["ground_truth_parameters"]
    assert man["transport"] == {**man["transport"], "indirect_samples": 2, "bounces": 1}
    for kw, needle in ((dict(material_mix="conductor", indirect_samples=2), "materials: heldout there"),
                       (dict(material_mix="heldout", indirect_samples=0), "indirect samples: 2 there"),
                       (dict(), "materials")):
        with pytest.raises(ConfigError, match=needle):
            generate_dataset(out, count=3, width=16, seed=1, shard_size=2, progress=False, **kw)
    assert generate_dataset(out, count=3, width=16, seed=1, shard_size=2, progress=False,
                            material_mix="heldout", indirect_samples=2) == {"written": 1, "skipped": 1}
    kinds = {MATERIAL_KINDS[k] for k in load_shard(out / shard_name(0))["material_kind"]}
    assert kinds <= {"film", "depolarizing"}
    # a set made before the mixes existed (no "materials"/"transport") resumes as baek, 0
    old = tmp_path / "old"
    generate_dataset(old, count=2, width=16, seed=1, shard_size=1, progress=False, max_shards=1)
    man = json.loads((old / "manifest.json").read_text())
    del man["materials"], man["transport"]
    (old / "manifest.json").write_text(json.dumps(man))
    assert generate_dataset(old, count=2, width=16, seed=1, shard_size=1,
                            progress=False) == {"written": 1, "skipped": 1}
    with pytest.raises(ConfigError, match="material mix must be one of"):
        generate_dataset(tmp_path / "bad", count=2, width=16, material_mix="gold", progress=False)
    assert not (tmp_path / "bad").exists()


def test_cli_flags_end_to_end(tmp_path, capsys):
    out = tmp_path / "cli"
    assert main(["sim", "dataset", "--count", "3", "--size", "16", "--seed", "3", "--quiet",
                 "--materials", "conductor", "--indirect-samples", "2", "--out", str(out)]) == 0
    man = json.loads((out / "manifest.json").read_text())
    assert man["materials"]["mix"] == "conductor" and man["transport"]["indirect_samples"] == 2
    shard = load_shard(out / shard_name(0))
    assert set(shard["material_kind"].tolist()) == {MATERIAL_KINDS.index("conductor")}
    direct = make_sample(1, seed=3, width=16, height=16, material_mix="conductor", indirect_samples=2)
    np.testing.assert_array_equal(shard["mueller"][1], direct["mueller"])
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["sim", "dataset", "--count", "3", "--size", "16", "--materials", "gold", "--out",
              str(tmp_path / "x")])
    assert e.value.code == 2 and "invalid choice" in capsys.readouterr().err
    assert main(["sim", "dataset", "--count", "3", "--size", "16", "--seed", "3", "--quiet",
                 "--out", str(out)]) == 2
    assert "materials: conductor there, baek asked" in capsys.readouterr().err


def test_sim_option_indirect_samples_reaches_the_world(tmp_path):
    from polrig.app.rig import open_rig

    assert parse_options({})["indirect_samples"] == 0
    cfg = tmp_path / "rig.toml"
    cfg.write_text('[sim]\nscene = "crater"\nsize = "32x32"\nindirect_samples = 2\nclock_speed = inf\n')
    with open_rig(cfg) as rig:
        assert rig.truth.rig_parameters()["indirect_samples"] == 2
    rig = create_sim_rig({"scene": "crater", "size": (32, 32), "indirect_samples": 3, "open": False,
                          "clock_speed": float("inf")})
    assert rig.world.indirect_samples == 3
    assert rig.truth.rig_parameters()["indirect_samples"] == 3
    for bad in (-1, 1.5, True, "4", 5000):
        with pytest.raises(ConfigError, match="indirect_samples"):
            parse_options({"indirect_samples": bad}, where="rig.toml: [sim] ")
