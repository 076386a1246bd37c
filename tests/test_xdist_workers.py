"""The worker count of ``-n auto`` (``tests/conftest.py``): 1.5 per usable CPU, as memory allows."""

from __future__ import annotations

import os

import pytest

import conftest


@pytest.mark.parametrize(("cpus", "memory_gib", "workers"),
                         [(1, 64, 1), (2, 64, 3), (3, 64, 4), (16, 64, 24), (16, 16, 8), (2, 1, 1)])
def test_auto_workers_per_cpu_as_memory_allows(monkeypatch, cpus, memory_gib, workers):
    monkeypatch.delenv("PYTEST_XDIST_AUTO_NUM_WORKERS", raising=False)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cpus)))
    monkeypatch.setattr("psutil.cpu_count", lambda logical=True: 64)
    pages = {"SC_PAGE_SIZE": 4096, "SC_PHYS_PAGES": memory_gib * 2**30 // 4096}
    monkeypatch.setattr(os, "sysconf", lambda name: pages[name])
    assert conftest.pytest_xdist_auto_num_workers(None) == workers


def test_the_affinity_and_the_physical_cores_bound_the_cpus(monkeypatch):
    monkeypatch.delenv("PYTEST_XDIST_AUTO_NUM_WORKERS", raising=False)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)))
    monkeypatch.setattr("psutil.cpu_count", lambda logical=True: 2)  # two physical cores
    assert conftest.pytest_xdist_auto_num_workers(None) == 3


def test_the_environment_variable_is_left_to_xdist(monkeypatch):
    monkeypatch.setenv("PYTEST_XDIST_AUTO_NUM_WORKERS", "5")
    assert conftest.pytest_xdist_auto_num_workers(None) is None
