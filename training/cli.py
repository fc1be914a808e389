"""``medseg-train``: fit a segmentation model from a cohort."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

from medseg._cli import (
    EXIT_OK,
    add_dataset_arguments,
    command_parser,
    load_dataset,
    machine_cores,
    non_negative_float,
    parse_labels,
    positive_int,
    run_cli,
)
from medseg.progress import show_progress

# The model's defaults (ShapePriorSegmenter's keyword arguments), written out here so that
# --help answers without importing the segmenter (scikit-learn, pyvista, ...: seconds);
# tests/test_cli.py checks them against the model's signature, so the two cannot drift apart.
_DEFAULT = {
    "n_candidates": 15,
    "cliques": "knn",
    "orientation_weight": 1.0,
    "refine_levels": 2,
    "n_hypotheses": 4,
    "frame_passes": 0,
    "augment_poses": 2,
}


def build_parser() -> argparse.ArgumentParser:
    parser = command_parser(
        "medseg-train",
        "Train a segmentation model (landmarks in correspondence, one Random-Forest "
        "detector per landmark, a pose-invariant triplet shape prior) from an MSD / "
        "nnU-Net dataset folder, a CSV manifest, or 'phantom' (the embedded synthetic "
        "cohort).",
        seed=True,
    )
    parser.add_argument("-o", "--output", required=True, help="Model folder to write.")
    add_dataset_arguments(parser)
    parser.add_argument(
        "--landmarks",
        type=int,
        default=None,
        help="Landmarks per shape (N). Default: the phantom's own, else sized to the structure.",
    )
    parser.add_argument(
        "--candidates",
        type=positive_int,
        default=_DEFAULT["n_candidates"],
        help=f"Candidates per landmark (L). Default: {_DEFAULT['n_candidates']}.",
    )
    parser.add_argument(
        "--cliques",
        choices=("knn", "delaunay", "all"),
        default=_DEFAULT["cliques"],
        help=f"Triplet cliques of the shape prior. Default: {_DEFAULT['cliques']}.",
    )
    parser.add_argument(
        "--orientation-weight",
        type=non_negative_float,
        default=_DEFAULT["orientation_weight"],
        help="Weight of the handedness term of the prior; 0 is the paper's prior. "
        f"Default: {_DEFAULT['orientation_weight']:g}.",
    )
    parser.add_argument(
        "--refine-levels",
        type=int,
        choices=range(4),
        default=_DEFAULT["refine_levels"],
        help="Levels of the active-shape refinement of the MRF's landmarks; 0 keeps them, "
        f"as in the paper. Default: {_DEFAULT['refine_levels']}.",
    )
    parser.add_argument(
        "--hypotheses",
        type=positive_int,
        default=_DEFAULT["n_hypotheses"],
        help="MRF solutions refined per image; the one whose boundary profiles fit the image "
        f"best is kept. Default: {_DEFAULT['n_hypotheses']}.",
    )
    parser.add_argument(
        "--frame-passes",
        type=int,
        choices=range(4),
        default=_DEFAULT["frame_passes"],
        help="Passes of the inference in the shape's own frame after the first; 0 is the "
        f"paper's single pass. Default: {_DEFAULT['frame_passes']}.",
    )
    parser.add_argument(
        "--augment-poses",
        type=int,
        choices=range(11),
        default=_DEFAULT["augment_poses"],
        help="Copies of each training image in a random pose, size and field of view that the "
        "landmark detectors also learn from (0: the training images only). "
        f"Default: {_DEFAULT['augment_poses']}.",
    )
    parser.add_argument(
        "--no-boundary",
        action="store_true",
        help="Train without the regional stage (voxel classifier and graph cut in the shape's "
        "frame): the label maps are then the template warped onto the landmarks. Default: off.",
    )
    parser.add_argument(
        "--jobs",
        type=positive_int,
        default=machine_cores(),
        help="Parallel jobs (threads) for the forests. Default: the machine's cores "
        f"({machine_cores()} here).",
    )
    return parser


def _run(args: argparse.Namespace) -> int:
    from medseg.segmenter import ShapePriorSegmenter

    labels = parse_labels(args.label)
    cohort = load_dataset(args)
    start = time.perf_counter()
    model = ShapePriorSegmenter(
        args.landmarks,
        labels=labels,
        n_candidates=args.candidates,
        cliques=args.cliques,
        orientation_weight=args.orientation_weight,
        refine_levels=args.refine_levels,
        n_hypotheses=args.hypotheses,
        frame_passes=args.frame_passes,
        augment_poses=args.augment_poses,
        boundary=not args.no_boundary,
        random_state=args.seed,
        n_jobs=args.jobs,
    ).fit(cohort, progress=show_progress(args.quiet))
    model.save(args.output)
    elapsed = time.perf_counter() - start
    print(
        f"trained on {len(model.cases_)} of {len(cohort)} cases of {cohort.name!r}: "
        f"{model.landmarks_.shape[1]} landmarks, {len(model.prior_.cliques_)} cliques, "
        f"{elapsed:.0f} s; model written to {args.output}"
    )
    for case_id, reason in model.rejected_.items():
        print(f"  rejected {case_id}: {reason}", file=sys.stderr)
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_run, build_parser(), argv)
