"""``medseg-train``: fit a segmentation model from a cohort."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from medseg._cli import run_cli
from medseg.errors import MedsegError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="medseg-train",
        description=(
            "Train a segmentation model (landmarks, Random-Forest detectors, triplet shape "
            "prior) from an MSD / nnU-Net dataset folder or a CSV manifest. "
            "NOT BUILT YET: the model is tracked in issue 6."
        ),
    )
    parser.add_argument("dataset", help="MSD / nnU-Net folder or CSV manifest.")
    parser.add_argument("-o", "--output", required=True, help="Model folder to write.")
    return parser


def _run(args: argparse.Namespace) -> int:
    raise MedsegError("medseg-train is not built yet (the segmentation model is issue 6).")


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_run, build_parser(), argv)
