"""Training lineage: every run that trained a model's networks, carried from checkpoint to
checkpoint and into ``model.json`` (issue 32, item 4: training continues across sessions).

A run's checkpoint (``polrig train``, ``--data on-device``, the GPU lease) holds ``lineage``, the
runs before it (from the checkpoint or weights folder it started from) plus one entry per network
it trained so far (:func:`run_entries`), and ``totals``, the sums per network (:func:`totals`):
epochs, optimizer ``steps`` (the step counter a continued run goes on from) and seconds. The
export writes both into ``model.json``'s ``training``; :func:`polrig.models.sizes.model_record`
reads the minutes from there.

Entries written before this module existed (the shipped small model's hand-made lineage) have
no ``steps``; :func:`totals` counts theirs as 0. No torch here.
"""

from __future__ import annotations

import collections
import os
import platform
from typing import Any, Iterable, Mapping, Sequence

NETWORKS = ("pipnet", "pmmnet", "direct")


def run_entries(rows: Iterable[Mapping[str, Any]], *, run: str, start: str, steps_per_epoch: Mapping[str, int],
                data: str, device: str, hardware: str, optimizer: str, notes: str = "") -> list[dict[str, Any]]:
    """One lineage entry per network with log ``rows`` (``polrig train``'s ``log.csv`` rows: ``stage``,
    ``epoch``, ``epoch_s``, ``val_loss``) in this run: its ``epochs``, optimizer ``steps``
    (``steps_per_epoch[network]`` each), ``seconds``, ``final_val_loss``, and the run's
    ``run`` (output folder), ``start`` (``scratch``, ``warm``: new optimizer on given weights,
    ``continued``: weights and optimizer state of a checkpoint), ``data``, ``device``,
    ``hardware``, ``optimizer`` (``fresh`` or ``continued``) and ``notes``."""
    by_net: dict[str, list[Mapping[str, Any]]] = collections.defaultdict(list)
    for r in rows:
        by_net[str(r["stage"])].append(r)
    out = []
    for net in NETWORKS:
        rs = by_net.get(net)
        if not rs:
            continue
        val = rs[-1].get("val_loss")
        out.append({"network": net, "run": run, "start": start, "notes": notes, "epochs": len(rs),
                    "steps": len(rs) * int(steps_per_epoch[net]),
                    "seconds": round(sum(float(r["epoch_s"]) for r in rs), 3),
                    "final_val_loss": None if val in (None, "") else float(val),
                    "data": data, "device": device, "hardware": hardware, "optimizer": optimizer})
    return out


def totals(lineage: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, float]]:
    """Per network: ``epochs``, ``steps`` and ``seconds`` summed over the lineage."""
    out = {}
    for net in NETWORKS:
        rs = [r for r in lineage if r.get("network") == net]
        out[net] = {"epochs": int(sum(int(r.get("epochs") or 0) for r in rs)),
                    "steps": int(sum(int(r.get("steps") or 0) for r in rs)),
                    "seconds": round(float(sum(float(r.get("seconds") or 0.0) for r in rs)), 3)}
    return out


def hardware_line(device: str) -> str:
    """What trained: ``NVIDIA H200 (cuda), 16 CPU cores`` or ``CPU x86_64, 2 cores`` (the GPU's
    name from torch where ``device`` is ``cuda``)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    if device == "cuda":
        import torch

        return f"{torch.cuda.get_device_name(0)} (cuda), {cores} CPU cores"
    return f"CPU {platform.machine()}, {cores} cores"
