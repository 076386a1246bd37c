"""From one state to four: single-shot, hybrid (the network as the prior of 1-4 states) and the
reference solve on the model card's held-out sets (issue 33 item 4).

``python -m benchmarks continuum`` runs :mod:`polrig.models.continuum` with the settings of the
committed table (64 samples per set at 64x64, the 2- and 3-state search on 32; about 7.5 min on
2 CPUs) and writes ``benchmarks/results/continuum.md`` with its ``.json``: matrix PSNR (all object
pixels, and those with no clipped sample), forward Stokes L2, coverage within 2 sigma, the seen
state's treatments, and 3 against 4 states at equal capture time. Extra arguments go to
``python -m polrig.models.continuum`` (``--count 8`` for a quick look, ``--out`` elsewhere).
"""

from __future__ import annotations

import pathlib
import sys

from polrig.models import continuum

RESULTS = pathlib.Path(__file__).resolve().parent / "results" / "continuum.md"
DEFAULTS = ["--count", "64", "--search-count", "32", "--out", str(RESULTS)]


def main(argv: list[str] | None = None) -> int:
    extra = list(sys.argv[1:] if argv is None else argv)
    return continuum.main(DEFAULTS + extra)  # later options win (argparse)


if __name__ == "__main__":
    sys.exit(main())
