"""``medseg-match``: dense correspondence between two surfaces."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

from medseg._cli import command_parser, run_cli

# The matcher (numpy, scipy, potpourri3d, pyvista, ...) is imported by the functions that
# use it, so that --help and argument errors answer at once (tests/test_cli.py checks).


def build_parser() -> argparse.ArgumentParser:
    parser = command_parser(
        "medseg-match",
        "Match surface A onto surface B with third-order graph matching (Zeng et al., "
        "CVPR 2010): sparse matching of farthest-point samples, dense candidates from "
        "Möbius maps (and, with --dense-stage, the paper's dense matching over them), "
        "spectral refinement. Writes one line per vertex of "
        "A with the 0-based index of its match on B. Both surfaces must be genus-0 "
        "triangle meshes (closed, or with holes); units do not matter (each surface is "
        "scaled to unit area) unless --partial.",
        seed=True,
    )
    parser.add_argument("source", help="Surface A (.off, .ply, .obj, .stl, .vtk, .vtp).")
    parser.add_argument("target", help="Surface B (same formats).")
    parser.add_argument("-o", "--output", required=True, help="Vertex map A -> B (text) to write.")
    parser.add_argument(
        "--inverse",
        default=None,
        help="Also write the map B -> A (one line per vertex of B). Default: not written.",
    )
    parser.add_argument(
        "--n-sparse", type=int, default=30, help="Sparse points on A (default: 30)."
    )
    parser.add_argument(
        "--n-targets",
        type=int,
        default=150,
        help="Farthest-point samples of B the sparse points may match (default: 150).",
    )
    parser.add_argument(
        "--n-solves",
        type=int,
        default=2,
        help=(
            "Sparse solves; each after the first excludes the earlier matches, and the "
            "map with the best descriptor agreement that is not a mirror image is kept "
            "(default: 2; 1 is about twice as fast, with more left-right flips)."
        ),
    )
    parser.add_argument(
        "--partial",
        action="store_true",
        help=(
            "One surface may be only part of the other (both in the same units): vertices "
            "without a partner get -1 in the maps (default: every vertex is mapped; "
            "experimental, see the README)."
        ),
    )
    parser.add_argument(
        "--dense-stage",
        action="store_true",
        help=(
            "Run the paper's dense stage (a third-order MRF over every vertex's candidates) "
            "before the refinement; once refined its maps were no better, at about a sixth "
            "more time (default: off)."
        ),
    )
    parser.add_argument(
        "--no-refine",
        action="store_true",
        help="Skip the spectral (ZoomOut) refinement of the dense map (default: refine).",
    )
    return parser


def _write_map(path: str, values, protect: Sequence[str]) -> None:
    import numpy as np

    from medseg.io import atomic_write

    with atomic_write(path, protect=protect) as tmp:
        np.savetxt(tmp, values, fmt="%d")


def _run(args: argparse.Namespace) -> int:
    from medseg.io import check_not_protected
    from medseg.matching import check_mesh, match_surfaces, read_mesh
    from medseg.progress import show_progress

    inputs = [args.source, args.target]
    for out in (args.output, args.inverse):
        if out is not None:
            check_not_protected(out, inputs)
    start = time.perf_counter()
    va, fa = read_mesh(args.source)
    vb, fb = read_mesh(args.target)
    # the matcher checks them again as "surface A / B": check here so errors name the files
    check_mesh(va, fa, name=args.source)
    check_mesh(vb, fb, name=args.target)
    result = match_surfaces(
        va,
        fa,
        vb,
        fb,
        n_sparse=args.n_sparse,
        n_sparse_targets=max(args.n_targets, args.n_sparse),
        n_solves=args.n_solves,
        refine=not args.no_refine,
        dense_stage=args.dense_stage,
        partial=args.partial,
        random_state=args.seed,
        progress=show_progress(args.quiet),
    )
    _write_map(args.output, result.forward, inputs)
    if args.inverse is not None:
        _write_map(args.inverse, result.inverse, inputs)
    elapsed = time.perf_counter() - start
    s, d = result.sparse, result.dense
    print(
        f"matched {len(va)} -> {len(vb)} vertices in {elapsed:.1f} s\n"
        f"sparse stage: {len(result.sparse_pairs)} pairs, energy {s.energy:.4g}, "
        f"lower bound {s.lower_bound:.4g}, gap {s.gap:.3f}, {s.n_iter} iterations\n"
        + (
            "dense stage: not run (each vertex on its best candidate; --dense-stage runs it)\n"
            if d is None
            else f"dense stage: energy {d.energy:.4g}, lower bound {d.lower_bound:.4g}, "
            f"gap {d.gap:.3f}, {d.n_iter} iterations, "
            f"{100 * result.matched_fraction:.1f}% of vertices matched by the dense stage\n"
        )
        + f"{len(result.solves)} sparse solve(s); {100 * result.mirrored_fraction:.1f}% of "
        "the surface mirrored by the map kept\n"
        + (
            f"{int((~result.matched).sum())} vertices of A and "
            f"{int((result.inverse < 0).sum())} of B without a partner\n"
            if args.partial
            else ""
        )
        + f"wrote {args.output}"
        + (f" and {args.inverse}" if args.inverse else ""),
        file=sys.stdout,
    )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_run, build_parser(), argv)
