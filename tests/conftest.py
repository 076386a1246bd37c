"""Shared test fixtures. Paths to the shared real data live here."""

from __future__ import annotations

import os
import pathlib

import pytest

# Qt widgets render offscreen in tests (CI has no display).
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

from hypothesis import settings  # noqa: E402

# No per-example deadline (a loaded 2-core machine must not turn slow examples into failures);
# in CI the examples are derandomized so a run is reproducible, while local runs keep exploring.
settings.register_profile("dev", deadline=None)
settings.register_profile("ci", deadline=None, derandomize=True, print_blob=True)
settings.load_profile("ci" if os.environ.get("CI") else "dev")

REPO = pathlib.Path(__file__).resolve().parents[1]
SHARED = pathlib.Path(os.environ.get("POLRIG_SHARED", REPO.parent / "shared"))
REAL_DOFP = SHARED / "data" / "real-dofp"


@pytest.fixture(scope="session")
def real_dofp_dir() -> pathlib.Path:
    if not REAL_DOFP.is_dir():
        pytest.fail(f"real DoFP frames not found at {REAL_DOFP} (set POLRIG_SHARED)")
    return REAL_DOFP


@pytest.fixture(scope="session")
def tiny_train_data(tmp_path_factory) -> pathlib.Path:
    """A 4-sample 32x32 training set (seed 0, 2 shards) for the training tests; read only
    (tests that damage data copy it first)."""
    from sim.dataset import generate_dataset

    root = tmp_path_factory.mktemp("tiny_train") / "data"
    generate_dataset(root, count=4, width=32, seed=0, shard_size=2, progress=False)
    return root
