"""``medseg-match``: dense correspondence between two surfaces."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from medseg._cli import run_cli
from medseg.errors import MedsegError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="medseg-match",
        description=(
            "Match surface A onto surface B with third-order graph matching; writes one line "
            "per vertex of A with the 0-based index of its match on B. "
            "NOT BUILT YET: tracked in issue 8."
        ),
    )
    parser.add_argument("source", help="Surface A (.off, .ply, .obj, .stl, .vtk, .vtp).")
    parser.add_argument("target", help="Surface B.")
    parser.add_argument("-o", "--output", required=True, help="Vertex map (text) to write.")
    return parser


def _run(args: argparse.Namespace) -> int:
    raise MedsegError("medseg-match is not built yet (the surface matcher is issue 8).")


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_run, build_parser(), argv)
