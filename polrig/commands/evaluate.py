"""``polrig evaluate --data DIR``: the single-shot model's held-out evaluation (the paper's two
tables: full model, PIPNet-pBRDF, best-fit pBRDF, direct Stokes->MM, four-state reference).

Thin shell over :func:`models.evaluate.evaluate` (metric definitions there); onnxruntime only.
"""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="evaluate the single-shot model on a held-out simulated set",
                       description="Run the shipped (or given) single-shot ONNX graphs and the "
                                   "baselines on a `polrig sim dataset --holdout` folder and write "
                                   "the paper's two tables as Markdown (+ JSON).")
    p.add_argument("--data", required=True, help="held-out dataset folder")
    p.add_argument("--weights", default=None, help="folder with single_shot.onnx and direct.onnx "
                                                   "(default: the shipped models/weights)")
    p.add_argument("--out", default="benchmarks/results/single_shot.md", help="Markdown output file")
    p.add_argument("--limit", type=int, default=None, help="evaluate at most this many samples")
    p.add_argument("--seed", type=int, default=0, help="seed of the reference-noise and pixel sampling")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from models.evaluate import evaluate, write_results

    if args.limit is not None and args.limit < 1:
        raise ValueError("--limit must be >= 1")
    result = evaluate(args.data, args.weights, limit=args.limit, seed=args.seed)
    write_results(result, args.out)
    print(f"wrote {args.out}")
    return 0
