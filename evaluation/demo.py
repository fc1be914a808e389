"""``medseg-demo``: the whole pipeline on the embedded synthetic phantom cohort.

Generates a phantom cohort (no download), trains a model on some subjects, segments the
held-out ones with no pose initialisation, and prints their Dice, HD95 and landmark errors,
with the detection-only baseline (no shape prior) beside them. Everything it makes goes to
one folder: the cohort in MSD layout (so every CLI can be tried on it), the model, and the
predicted label maps.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path

from medseg._cli import EXIT_OK, command_parser, run_cli
from medseg.errors import MedsegError

# The pipeline (scikit-learn, SimpleITK, pyvista, ...) is imported by _run, so that --help
# and argument errors answer at once (tests/test_cli.py checks).


def build_parser() -> argparse.ArgumentParser:
    parser = command_parser(
        "medseg-demo",
        "Train on a synthetic phantom cohort and segment held-out phantom cases; prints "
        "Dice, HD95 and landmark error with and without the shape prior.",
        seed=True,
    )
    parser.add_argument(
        "-o", "--output", default="medseg-demo", help="Folder to write. Default: medseg-demo."
    )
    parser.add_argument("--subjects", type=int, default=20, help="Phantom subjects. Default: 20.")
    parser.add_argument("--test", type=int, default=5, help="Held-out subjects. Default: 5.")
    parser.add_argument("--jobs", type=int, default=2, help="Parallel jobs. Default: 2.")
    return parser


def _run(args: argparse.Namespace) -> int:
    if not 1 <= args.test < args.subjects:
        raise MedsegError("--test must be at least 1 and less than --subjects")
    import numpy as np
    from tqdm.auto import tqdm

    from medseg.datasets import make_phantom_cohort, write_cohort
    from medseg.evaluation.metrics import landmark_errors, score_segmentation
    from medseg.io import select_labels, write_image
    from medseg.progress import show_progress
    from medseg.segmenter import ShapePriorSegmenter

    progress = show_progress(args.quiet)
    out = Path(args.output)
    start = time.perf_counter()
    cohort = make_phantom_cohort(args.subjects, random_state=args.seed)
    write_cohort(cohort, out / "phantom", overwrite=True)
    train, test = cohort[: -args.test], cohort[-args.test :]
    print(f"phantom cohort: {len(cohort)} subjects written to {out / 'phantom'}")

    t0 = time.perf_counter()
    model = ShapePriorSegmenter(random_state=args.seed, n_jobs=args.jobs)
    model.fit(train, progress=progress)
    model.save(out / "model")
    print(
        f"trained on {len(train)} subjects in {time.perf_counter() - t0:.0f} s: "
        f"{model.landmarks_.shape[1]} landmarks, {len(model.prior_.cliques_)} triplet cliques"
    )

    header = (
        f"{'case':<14}{'method':<16}{'Dice':>7}{'HD95 mm':>9}{'LM err mm':>11}"
        f"{'LM err vox':>11}{'gap':>10}{'time s':>8}"
    )
    print(header)
    rows = []
    for case in tqdm(test, desc="segmenting", disable=not progress):
        image = case.load_image()
        truth = select_labels(case.load_label(), 1)
        cands = None
        for method, use_prior in (("shape prior", True), ("detection only", False)):
            seg = model.segment(image, use_prior=use_prior, candidates=cands)
            cands = seg.candidates
            scores = score_segmentation(seg.label, truth)
            err_mm, err_vox = landmark_errors(seg.landmarks, case.load_landmarks(), image)
            gap = f"{seg.mrf.gap:.1e}" if seg.mrf is not None else "-"
            seconds = sum(seg.timings.values())
            print(
                f"{case.case_id:<14}{method:<16}{scores.dice:>7.3f}{scores.hd95:>9.2f}"
                f"{err_mm.mean():>11.2f}{err_vox.mean():>11.2f}{gap:>10}{seconds:>8.1f}"
            )
            rows.append((method, scores.dice, err_vox.mean()))
            if use_prior:
                write_image(seg.label, out / "predictions" / f"{case.case_id}.nii.gz")
    for method in ("shape prior", "detection only"):
        dice = np.mean([r[1] for r in rows if r[0] == method])
        err = np.mean([r[2] for r in rows if r[0] == method])
        print(f"mean {method:<16} Dice {dice:.3f}   landmark error {err:.2f} voxels")
    print(f"done in {time.perf_counter() - start:.0f} s; outputs in {out}")
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_run, build_parser(), argv)
