"""Wall time of the evaluation engine, serial against parallel folds.

Runs :func:`medseg.evaluation.run_evaluation` on a cohort (default: the embedded phantom) into
fresh folders under ``--out`` (default: a temporary folder), once per ``--n-jobs`` value,
and prints the wall time, the speed-up over the first value, and the summary table of the
last run. The numbers are identical across runs (same seed); only the time differs.

Examples
--------
python benchmarks/bench_evaluation.py --methods asm --folds loo --n-jobs 1 2
python benchmarks/bench_evaluation.py --methods shape_prior detection asm --folds 5 \
    --n-jobs 2 --perturbation rot45 scale0.8 random
python benchmarks/bench_evaluation.py --cohort ../shared/data/hippocampus --labels 1 2 \
    --folds 5 --n-jobs 2
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from medseg.evaluation import resolve_cohort, run_evaluation


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cohort", default="phantom", help="Default: phantom.")
    parser.add_argument("--methods", nargs="+", default=["shape_prior", "detection", "asm"])
    parser.add_argument("--folds", default="5", help="'loo' or k. Default: 5.")
    parser.add_argument("--labels", nargs="+", type=int, default=[1])
    parser.add_argument("--n-jobs", nargs="+", type=int, default=[1, 2])
    parser.add_argument(
        "--perturbation", nargs="*", default=[], help="condition names, e.g. rot90 random"
    )
    parser.add_argument("--max-subjects", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--n-estimators", type=int, default=None, help="Trees per landmark forest. Default: 60."
    )
    parser.add_argument("--out", default=None, help="Default: a temporary folder.")
    args = parser.parse_args()
    folds = args.folds if args.folds == "loo" else int(args.folds)
    root = Path(args.out or tempfile.mkdtemp(prefix="bench_evaluation_"))
    cohort = resolve_cohort(args.cohort, seed=args.seed, max_subjects=args.max_subjects)
    print(f"{cohort!r}; folds={folds}; methods={args.methods}; output under {root}")
    times = []
    for n_jobs in args.n_jobs:
        out = root / f"n_jobs_{n_jobs}"
        t0 = time.perf_counter()
        run_evaluation(
            cohort,
            out,
            folds=folds,
            methods=args.methods,
            labels=args.labels,
            seed=args.seed,
            n_jobs=n_jobs,
            perturbation=args.perturbation,
            segmenter_params=(
                {"n_estimators": args.n_estimators} if args.n_estimators is not None else None
            ),
        )
        times.append(time.perf_counter() - t0)
        print(
            f"n_jobs={n_jobs}: {times[-1]:.1f} s wall "
            f"(speed-up {times[0] / times[-1]:.2f}x over n_jobs={args.n_jobs[0]})",
            flush=True,
        )
    print((out / "summary.md").read_text())


if __name__ == "__main__":
    main()
