"""Shared plumbing for the command-line tools: parsers, one-line errors, exit codes, types.

Only the stage packages (``medseg.training``, ``medseg.inference``, ``medseg.evaluation``)
and ``python -m`` entry points import this; the library's parts do not (an import contract).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from medseg.errors import MedsegError

EXIT_OK = 0
EXIT_FAILURE = 1  # the run went through but some items failed (e.g. one file of a batch)
EXIT_USAGE = 2  # bad input: nothing was done


def command_parser(prog: str, description: str, *, seed: bool = False) -> argparse.ArgumentParser:
    """The parser of a medseg command, with the options every command shares.

    ``-q/--quiet`` (no progress bars) and, for a command that draws random numbers,
    ``--seed`` (default 0). They stand in a group of their own ("common options"), which
    ``--help`` lists after the command's own options.
    """
    parser = argparse.ArgumentParser(prog=prog, description=description)
    common = parser.add_argument_group("common options")
    if seed:
        common.add_argument("--seed", type=int, default=0, help="Random seed. Default: 0.")
    common.add_argument("-q", "--quiet", action="store_true", help="No progress bars.")
    return parser


def add_dataset_arguments(parser: argparse.ArgumentParser) -> None:
    """DATASET, ``--label`` and ``--phantom-subjects``: the cohort a command reads.

    :func:`load_dataset` turns them into a cohort, :func:`parse_labels` the label text into
    labels. The parser needs ``--seed`` too (the phantom's seed).
    """
    parser.add_argument(
        "dataset",
        help="MSD / nnU-Net folder (dataset.json), CSV manifest, or 'phantom' (the embedded "
        "synthetic cohort).",
    )
    parser.add_argument(
        "--label",
        default="1",
        help="Label(s) forming the structure, comma-separated, e.g. 1,2. Default: 1.",
    )
    parser.add_argument(
        "--phantom-subjects",
        type=int,
        default=20,
        help="Subjects of the phantom cohort when DATASET is 'phantom'. Default: 20.",
    )


def load_dataset(args: argparse.Namespace):
    """The cohort of :func:`add_dataset_arguments`: the phantom, or a folder or manifest."""
    from medseg.datasets import load_cohort, make_phantom_cohort

    if args.dataset == "phantom":
        return make_phantom_cohort(args.phantom_subjects, random_state=args.seed)
    return load_cohort(args.dataset)


def run_cli(
    body: Callable[[argparse.Namespace], int],
    parser: argparse.ArgumentParser,
    argv: Sequence[str] | None,
) -> int:
    """Parse ``argv`` and run ``body``; a :class:`MedsegError` becomes one line on stderr.

    ``KeyboardInterrupt`` also ends in one line and exit code 130. Any other exception is a
    bug in medseg and keeps its traceback.
    """
    args = parser.parse_args(argv)
    try:
        return int(body(args))
    except MedsegError as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"{parser.prog}: interrupted", file=sys.stderr)
        return 130


def parse_labels(text: str) -> tuple[int, ...]:
    """``"1,2"`` -> ``(1, 2)``; a clear error for anything else."""
    try:
        labels = tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError:
        labels = ()
    if not labels or min(labels) < 1:
        raise MedsegError(
            f"--label {text!r} is not a comma-separated list of positive integers (e.g. 1,2)"
        )
    return labels


def machine_cores() -> int:
    """The machine's cores (``os.cpu_count()``, 1 if unknown): the default of ``--jobs``."""
    return os.cpu_count() or 1


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (a bad value is argparse's one-line usage error)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer >= 1")
    return value


def non_negative_float(text: str) -> float:
    """argparse type: a finite number >= 0."""
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not (value >= 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number >= 0")
    return value


def naming(exc: MedsegError, source: str | os.PathLike) -> MedsegError:
    """``exc`` itself if its message names ``source``, else the same error prefixed with it.

    Errors raised deep in the pipeline (a degenerate landmark set, a feature map that
    overflows) do not know which file they came from; the CLI does.
    """
    message = str(exc)
    if str(source) in message or Path(source).name in message:
        return exc
    return type(exc)(f"{source}: {message}")
