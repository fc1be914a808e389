"""``medseg-segment``: segment NIfTI (or any SimpleITK-readable) images with a trained model."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from medseg._cli import run_cli
from medseg.errors import MedsegError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="medseg-segment",
        description=(
            "Segment an image or a folder of images with a trained model; the label map is "
            "written in the input's geometry. NOT BUILT YET: tracked in issue 6."
        ),
    )
    parser.add_argument("-m", "--model", required=True, help="Model folder from medseg-train.")
    parser.add_argument("-i", "--input", required=True, help="Image file or folder.")
    parser.add_argument("-o", "--output", required=True, help="Output file or folder.")
    return parser


def _run(args: argparse.Namespace) -> int:
    raise MedsegError("medseg-segment is not built yet (the segmentation model is issue 6).")


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_run, build_parser(), argv)
