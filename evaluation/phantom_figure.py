"""``python -m medseg.evaluation.phantom_figure OUT.png``: slices of phantom subjects.

Draws the figure of ``docs/phantom.png`` (:func:`medseg.viz.save_cohort_png` on the
embedded phantom cohort).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from medseg._cli import EXIT_OK, command_parser, run_cli
from medseg.datasets import make_phantom_cohort
from medseg.viz import save_cohort_png


def build_parser() -> argparse.ArgumentParser:
    parser = command_parser(
        "python -m medseg.evaluation.phantom_figure",
        "Draw slices of synthetic phantom subjects with their labels as a PNG.",
        seed=True,
    )
    parser.add_argument("output", type=Path, help="PNG file to write.")
    parser.add_argument("--n-cases", type=int, default=3, help="Subjects to draw. Default: 3.")
    parser.add_argument(
        "--anisotropic", action="store_true", help="1 x 1 x 2 mm phantom. Default: 1 mm."
    )
    parser.add_argument("--axis", type=int, default=0, help="Array axis to cut. Default: 0 (z).")
    return parser


def _run(args: argparse.Namespace) -> int:
    cohort = make_phantom_cohort(args.n_cases, anisotropic=args.anisotropic, random_state=args.seed)
    save_cohort_png(cohort, args.output, n_cases=args.n_cases, axis=args.axis)
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_run, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
