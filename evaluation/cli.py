"""``medseg-evaluate``: cross-validation by subject with baselines, metrics and a report."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from medseg._cli import (
    EXIT_OK,
    add_dataset_arguments,
    command_parser,
    load_dataset,
    parse_labels,
    run_cli,
)
from medseg.errors import MedsegError
from medseg.progress import show_progress


def build_parser() -> argparse.ArgumentParser:
    # the light module of the defaults, not the evaluation (scikit-learn, matplotlib, ...)
    from medseg.evaluation.methods import DEFAULT_METHODS, DEFAULT_PERTURBATION, METHOD_NAMES

    parser = command_parser(
        "medseg-evaluate",
        "Leave-one-subject-out or k-fold cross-validation (grouped by subject) of the "
        "shape-prior segmenter and its baselines (detection without prior, active shape "
        "model; optionally multi-atlas registration), with a pose-perturbation study. "
        "Writes a report folder: cases.csv, summary.md, summary.json, boxplots, "
        "perturbation curves, overlays. Rerunning on the same folder resumes.",
        seed=True,
    )
    parser.add_argument("-o", "--output", required=True, help="Report folder.")
    add_dataset_arguments(parser)
    parser.add_argument(
        "--folds", default="loo", help="'loo' or the number K of subject folds. Default: loo."
    )
    parser.add_argument(
        "--methods",
        default=",".join(DEFAULT_METHODS),
        help=f"Comma-separated methods among {','.join(METHOD_NAMES)}. "
        f"Default: {','.join(DEFAULT_METHODS)}.",
    )
    parser.add_argument(
        "--landmarks", type=int, default=None, help="Landmarks per shape. Default: automatic."
    )
    parser.add_argument(
        "--perturbation",
        default=",".join(DEFAULT_PERTURBATION),
        help=(
            "Conditions of the pose-perturbation study, comma-separated: rotN (rotation by "
            "N degrees, 0-180), scaleS (0.5 < S < 2), pad_zeros, pad_noise (15 mm larger "
            "field of view), random (up to 45 degrees and x0.8-1.25); 'none' skips it. "
            "Default: " + ",".join(DEFAULT_PERTURBATION)
        ),
    )
    parser.add_argument(
        "--max-subjects",
        type=int,
        default=None,
        help="Evaluate only the first N subjects. Default: all.",
    )
    parser.add_argument("--jobs", type=int, default=1, help="Folds in parallel. Default: 1.")
    parser.add_argument(
        "--keep-models",
        action="store_true",
        help="Keep each fold's fitted segmenter in OUTPUT/models and reuse it when the run is "
        "resumed or extended (same cases, settings, seed and medseg source), instead of "
        "fitting it again.",
    )
    parser.add_argument(
        "--scheduler",
        default=None,
        help="Address of a running Dask scheduler (tcp://host:port). Default: local.",
    )
    return parser


def _folds(text: str):
    if text == "loo":
        return "loo"
    try:
        k = int(text)
    except ValueError:
        k = 0
    if k < 2:
        raise MedsegError(f"--folds {text!r}: give 'loo' or a whole number of folds >= 2")
    return k


def _conditions(text: str) -> tuple[str, ...]:
    from medseg.evaluation.perturbation import parse_condition

    if text.strip().lower() in ("", "none"):
        return ()
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    for name in names:
        try:
            parse_condition(name)
        except MedsegError as exc:
            raise MedsegError(f"--perturbation: {exc}") from None
    return names


def _run(args: argparse.Namespace) -> int:
    from medseg.evaluation.evaluate import run_evaluation

    # the arguments' text first: a typo is reported before the cohort is read
    folds, labels = _folds(args.folds), parse_labels(args.label)
    conditions = _conditions(args.perturbation)
    out = run_evaluation(
        load_dataset(args),
        args.output,
        folds=folds,
        methods=[m.strip() for m in args.methods.split(",") if m.strip()],
        labels=labels,
        n_landmarks=args.landmarks,
        seed=args.seed,
        n_jobs=args.jobs,
        scheduler=args.scheduler,
        keep_models=args.keep_models,
        perturbation=conditions,
        max_subjects=args.max_subjects,
        progress=show_progress(args.quiet),
    )
    summary = out / "summary.md"
    if summary.is_file() and not args.quiet:
        print(summary.read_text(encoding="utf-8"))
    print(f"report written to {out}")
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_run, build_parser(), argv)
