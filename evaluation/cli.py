"""``medseg-evaluate``: cross-validation with baselines, metrics and a report."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from medseg._cli import run_cli
from medseg.errors import MedsegError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="medseg-evaluate",
        description=(
            "Leave-one-out / k-fold evaluation by subject with baselines and a report. "
            "NOT BUILT YET: tracked in issue 7."
        ),
    )
    parser.add_argument("dataset", help="MSD / nnU-Net folder, CSV manifest, or 'phantom'.")
    parser.add_argument("-o", "--output", required=True, help="Report folder.")
    return parser


def _run(args: argparse.Namespace) -> int:
    raise MedsegError("medseg-evaluate is not built yet (evaluation is issue 7).")


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_run, build_parser(), argv)
