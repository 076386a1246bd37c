"""From one state to four: single-shot, hybrid (the network as the prior of 1-4 states) and the
reference solve on the model card's held-out sets (issue 33 item 4).

``python -m benchmarks continuum`` runs :mod:`polrig.models.continuum` with the settings of the
committed table (64 samples per set at 64x64, the 2- and 3-state search on 32; 60-75 min on
2 shared CPUs: 3587 s for the committed run, 4440 s on 2026-12-01) and writes
``benchmarks/results/continuum.md`` with its ``.json`` and the accuracy-against-time plot
``.png``: matrix PSNR (all object pixels, and those with no clipped sample), forward Stokes L2,
coverage within 2 sigma, the seen state's treatment, and 3 against 4 states at equal capture
time. Extra arguments go to ``python -m polrig.models.continuum`` (``--count 8`` for a quick
look, ``--out`` elsewhere).

``python benchmarks/bench_continuum.py --plot-only`` redraws ``continuum.png`` from the committed
``continuum.json`` alone (seconds). ``--rig`` scores the default simulated rig's scenes at its size
instead (:data:`polrig.models.continuum.RIG_SCENES` at the 128x128 analyzer grid of its 512x512
colour sensor, six turntable angles 0..300 deg, the states searched at 64x64; 18-22 min on 2
shared CPUs) into ``benchmarks/results/continuum_rig.md`` (``.json``, ``.png``). ``--models``
runs only the lower-order model comparison at two states (0/90: single-shot, hybrid 2, hybrid 2
with ``select_models``, its diffuse completion, and the diffuse term tested on the samples alone,
``polrig.solve.diffuse_test``; 64 samples per set; about 22 min on 2 shared CPUs) into
``benchmarks/results/continuum_models.md`` (``.json``); the full run holds it too, as its last
table. ``--joint`` compares the per-element prior with the joint one (``joint_prior`` in
``uncertainty.json``; ``--joint-compare``: the two-state test's false acceptance, coverage and
PSNR at 1-4 states; 64 samples per set, about 22 min) into ``benchmarks/results/continuum_joint.md``,
``--joint --rig`` on the rig's scenes at three turntable angles (about 5 min) into
``continuum_joint_rig.md``. ``--min-states`` runs the adaptive capture on the rig's scenes (six
turntable angles, both targets) with a pose allowed to stop from its second state (the capture's
default) and from its third (``--min-states 3``; about 9 min) into
``benchmarks/results/continuum_min_states.md`` (``.json``).
"""

from __future__ import annotations

import pathlib
import sys

from polrig.models import continuum

RESULTS = pathlib.Path(__file__).resolve().parent / "results" / "continuum.md"
RIG_RESULTS = RESULTS.with_name("continuum_rig.md")
DEFAULTS = ["--count", "64", "--search-count", "32", "--out", str(RESULTS)]
RIG_DEFAULTS = ["--rig-scenes", ",".join(continuum.RIG_SCENES), "--out", str(RIG_RESULTS)]
MODELS_RESULTS = RESULTS.with_name("continuum_models.md")
MODELS_DEFAULTS = ["--models-only", "--count", "64", "--out", str(MODELS_RESULTS)]
JOINT_DEFAULTS = ["--joint-compare", "--count", "64", "--out", str(RESULTS.with_name("continuum_joint.md"))]
MIN_STATES_DEFAULTS = ["--min-states-compare", "--rig-scenes", ",".join(continuum.RIG_SCENES),
                       "--out", str(RESULTS.with_name("continuum_min_states.md"))]
JOINT_RIG_DEFAULTS = ["--joint-compare", "--rig-scenes", ",".join(continuum.RIG_SCENES), "--rig-poses", "0,120,240",
                      "--out", str(RESULTS.with_name("continuum_joint_rig.md"))]


def main(argv: list[str] | None = None) -> int:
    extra = list(sys.argv[1:] if argv is None else argv)
    if "--plot-only" in extra:
        i = extra.index("--plot-only")
        given = i + 1 < len(extra) and not extra[i + 1].startswith("--")
        return continuum.main(["--plot-only", extra[i + 1] if given else str(RESULTS.with_suffix(".json"))])
    if "--min-states" in extra:
        extra.remove("--min-states")
        return continuum.main(MIN_STATES_DEFAULTS + extra)
    if "--joint" in extra:
        extra.remove("--joint")
        if "--rig" in extra:
            extra.remove("--rig")
            return continuum.main(JOINT_RIG_DEFAULTS + extra)
        return continuum.main(JOINT_DEFAULTS + extra)
    if "--rig" in extra:
        extra.remove("--rig")
        return continuum.main(RIG_DEFAULTS + extra)
    if "--models" in extra:
        extra.remove("--models")
        return continuum.main(MODELS_DEFAULTS + extra)
    return continuum.main(DEFAULTS + extra)  # later options win (argparse)


if __name__ == "__main__":
    sys.exit(main())
