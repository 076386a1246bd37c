"""Shared test fixtures, and the paths of the test data kept in the repository."""

from __future__ import annotations

import os
import pathlib
import signal

import pytest

# Qt widgets render offscreen in tests (CI has no display).
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

from hypothesis import settings  # noqa: E402

# No per-example deadline (a loaded 2-core machine must not turn slow examples into failures);
# in CI the examples are derandomized so a run is reproducible, while local runs keep exploring.
settings.register_profile("dev", deadline=None)
settings.register_profile("ci", deadline=None, derandomize=True, print_blob=True)
settings.load_profile("ci" if os.environ.get("CI") else "dev")


#: Workers of ``-n auto`` per CPU: the suite waits on subprocesses (the CLI, Dask workers, a
#: training run), on the emulated devices' timing and on files, so one worker per CPU leaves them
#: idle part of the time (a warm run on 2 CPUs: 86 % busy with 2 workers). Measured on 2 CPUs,
#: whole suite, warm numba cache: 2 workers 661 s, 3 workers 565 s, 4 workers 605 s.
WORKERS_PER_CPU = 1.5
#: Memory one worker may need at its peak (bytes): a worker holds about 1.1 GiB after collection,
#: and some tests start subprocesses of their own; ``-n auto`` starts no more than the machine's
#: memory holds at this much each.
WORKER_MEMORY = 2 * 2**30


def pytest_xdist_auto_num_workers(config) -> int | None:
    """Workers of ``-n auto`` (pyproject.toml's addopts): :data:`WORKERS_PER_CPU` times the CPUs
    this process may run on (its affinity: ``taskset``, a container's cpuset; at most the physical
    cores), rounded down, and no more than the machine's memory holds at :data:`WORKER_MEMORY`
    each; one on one CPU. pytest-xdist's own count (psutil's physical cores) ignores the
    affinity: pinned to one CPU it started two workers on it. ``PYTEST_XDIST_AUTO_NUM_WORKERS=N``
    still sets the count (xdist's rule)."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS") or not hasattr(os, "sched_getaffinity"):
        return None  # xdist's own rule
    cpus = len(os.sched_getaffinity(0))
    try:
        import psutil
    except ImportError:
        pass
    else:
        cpus = max(1, min(cpus, psutil.cpu_count(logical=False) or cpus))
    if cpus == 1:
        return 1
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError):
        memory = None
    workers = int(cpus * WORKERS_PER_CPU)
    return max(1, min(workers, memory // WORKER_MEMORY)) if memory else workers


REPO = pathlib.Path(__file__).resolve().parents[1]
#: Real IMX250MZR raw frames with their licence (tests/data/real-dofp/README.md).
REAL_DOFP = REPO / "tests" / "data" / "real-dofp"


@pytest.fixture(scope="session", autouse=True)
def sigint_raises_keyboard_interrupt():
    """SIGINT raises ``KeyboardInterrupt`` here and in the processes the tests start, as in a
    terminal. A shell starts a background job with SIGINT ignored, Python then keeps it ignored,
    and children inherit that; the tests that deliver SIGINT (an operator's Ctrl-C) install the
    handler they rely on instead of inheriting it (a child's exec resets a handler to the
    default, so child processes get Python's own)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.fixture(scope="session")
def real_dofp_dir() -> pathlib.Path:
    if not REAL_DOFP.is_dir():
        pytest.fail(f"real DoFP frames not found at {REAL_DOFP} (they are part of the repository)")
    return REAL_DOFP


@pytest.fixture(scope="session")
def tiny_train_data(tmp_path_factory) -> pathlib.Path:
    """A 4-sample 32x32 training set (seed 0, 2 shards) for the training tests; read only
    (tests that damage data copy it first)."""
    from polrig.sim.dataset import generate_dataset

    root = tmp_path_factory.mktemp("tiny_train") / "data"
    generate_dataset(root, count=4, width=32, seed=0, shard_size=2, progress=False)
    return root


@pytest.fixture
def viewer_panel(qtbot):
    """Make standalone :class:`polrig.gui.viewer.ViewerPanel` widgets: ``make(size=None,
    show=True)`` returns a new panel, resized to ``size`` (width, height px) and shown. At the
    test's teardown each is shut down (its load and ROI threads ended) before it is closed, as
    :meth:`polrig.gui.main_window.MainWindow.shutdown` does for the main window's viewer: a panel
    closed with its thread pools alive could still be handed a queued result while Qt destroys
    it."""
    from polrig.gui.viewer import ViewerPanel

    def make(size: tuple[int, int] | None = None, show: bool = True) -> ViewerPanel:
        v = ViewerPanel()
        qtbot.addWidget(v, before_close_func=lambda panel: panel.shutdown())
        if size is not None:
            v.resize(*size)
        if show:
            v.show()
        return v

    return make
