"""``polrig evaluate --data DIR``: the single-shot model's held-out evaluation (the paper's two
tables: full model, PIPNet-pBRDF, best-fit pBRDF, direct Stokes->MM, four-state reference).

Thin shell over :func:`polrig.models.evaluate.evaluate` (metric definitions there); onnxruntime only.
"""

from __future__ import annotations

import argparse

from polrig.formats.argcheck import int_range

#: Where the tables go unless --out says otherwise: a scratch path, so that a run on another set
#: or other weights never replaces the published tables in benchmarks/results/.
DEFAULT_OUT = "runs/evaluate/single_shot.md"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="evaluate the single-shot model on a held-out simulated set",
                       description="Run the shipped (or given) single-shot ONNX graphs and the "
                                   "baselines on a `polrig sim dataset --holdout` folder and write "
                                   "the paper's two tables as Markdown (+ JSON).")
    p.add_argument("--data", required=True, help="held-out dataset folder")
    p.add_argument("--weights", default=None, help="folder with single_shot.onnx and direct.onnx "
                                                   "(default: the shipped models/weights)")
    p.add_argument("--out", default=DEFAULT_OUT,
                   help=f"Markdown output file, .md (default {DEFAULT_OUT}); the numbers go next to it as .json; "
                        "both are replaced. The published tables are benchmarks/results/single_shot*.md: give "
                        "that path to re-score them")
    p.add_argument("--limit", type=int_range(1, 10**9), default=None,
                   help="evaluate at most the first this many samples")
    p.add_argument("--seed", type=int_range(0, 2**32 - 1), default=0,
                   help="seed of the reference-noise and pixel sampling")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from polrig.models.evaluate import evaluate, results_paths, write_results

    out_md, out_json = results_paths(args.out)  # before the evaluation: a bad --out costs nothing
    result = evaluate(args.data, args.weights, limit=args.limit, seed=args.seed)
    write_results(result, out_md)
    print(f"wrote {out_md} and {out_json}")
    return 0
