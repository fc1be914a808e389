"""Pose agreement end to end: one phantom image, and the same image moved and resampled.

Usage::

    python benchmarks/bench_pose.py [--model MODEL] [--angles 15,30] [--out pose.json]

Trains the default :class:`~medseg.segmenter.ShapePriorSegmenter` on the first phantom subjects
(the demo's split: 15 of 20, seed 0), unless ``--model`` gives a model trained on that
cohort. Each held-out image is segmented as it is and under a random similarity of each
angle (``medseg.evaluation.perturbation.random_similarity``: a rotation about a random axis and a
scale of up to 1.25, resampled on the image's own grid), with no initialisation of any
kind. The landmarks of the moved image are compared with those of the original, mapped
through the same similarity; a voxel is the largest spacing.

Reported per run and summarised: median disagreement (mm and voxels), the fraction of
landmarks within one voxel, for the MRF's choice (``Segmentation.chosen``) and the refined
landmarks (``Segmentation.landmarks``), and the landmark error of the unmoved run. The
issue's target is agreement within one voxel. Nothing is written into the repository.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from medseg.datasets import make_phantom_cohort
from medseg.evaluation.perturbation import perturb_case, random_similarity
from medseg.io import voxel_to_physical
from medseg.segmenter import ShapePriorSegmenter, load_model


def _centre(label: sitk.Image) -> np.ndarray:
    """The fixed point perturb_case uses by default: the label's foreground centroid."""
    fg = np.argwhere(sitk.GetArrayViewFromImage(label) > 0)
    return voxel_to_physical(label, fg).mean(axis=0)


def _agreement(a: np.ndarray, b: np.ndarray, change, centre, voxel: float) -> dict:
    d = np.linalg.norm(change.apply(a, centre) - b, axis=1)
    return {
        "median_mm": float(np.median(d)),
        "median_voxels": float(np.median(d) / voxel),
        "within_1_voxel": float(np.mean(d <= voxel)),
    }


def _summary(runs: list[dict], key: str) -> dict:
    medians = np.array([r[key]["median_voxels"] for r in runs])
    within = np.array([r[key]["within_1_voxel"] for r in runs])
    return {
        "median_of_medians_voxels": float(np.median(medians)),
        "mean_within_1_voxel": float(within.mean()),
        "runs_with_median_within_1_voxel": int((medians <= 1.0).sum()),
        "runs": len(runs),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, help="A model trained on the phantom split.")
    parser.add_argument("--subjects", type=int, default=20)
    parser.add_argument("--test", type=int, default=5, help="Held-out subjects (the last).")
    parser.add_argument("--angles", default="15,30")
    parser.add_argument(
        "--hypotheses", type=int, help="Override the model's n_hypotheses (to compare)."
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    angles = [float(a) for a in args.angles.split(",")]

    cohort = make_phantom_cohort(args.subjects, random_state=args.seed)
    train, test = cohort[: -args.test], cohort[-args.test :]
    if args.model is not None:
        model = load_model(args.model)
    else:
        t0 = time.perf_counter()
        model = ShapePriorSegmenter(random_state=args.seed, n_jobs=args.jobs).fit(train)
        print(f"trained in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    if args.hypotheses is not None:
        model.n_hypotheses = args.hypotheses
    leaked = set(model.cases_) & set(test.case_ids)
    if leaked:
        parser.error(f"the model was trained on test case(s) {sorted(leaked)}")

    runs = []
    for k, case in enumerate(test):
        image, label, truth = case.load_image(), case.load_label(), case.load_landmarks()
        voxel = float(max(image.GetSpacing()))
        centre = _centre(label)
        original = model.segment(image)
        error = float(np.linalg.norm(original.landmarks - truth, axis=1).mean())
        for angle in angles:
            change = random_similarity(angle, random_state=1000 * args.seed + 10 * k + int(angle))
            moved_image, _, _ = perturb_case(image, label, None, change, centre=centre)
            moved = model.segment(moved_image)
            run = {
                "case": case.case_id,
                "angle_deg": angle,
                "scale": change.scale,
                "error_unmoved_mm": error,
                "chosen": _agreement(original.chosen, moved.chosen, change, centre, voxel),
                "refined": _agreement(original.landmarks, moved.landmarks, change, centre, voxel),
            }
            runs.append(run)
            print(
                f"{case.case_id} {angle:g} deg: median disagreement chosen "
                f"{run['chosen']['median_voxels']:.2f} vox, refined "
                f"{run['refined']['median_voxels']:.2f} vox "
                f"({run['refined']['within_1_voxel']:.0%} within 1 voxel); error unmoved "
                f"{error:.2f} mm",
                file=sys.stderr,
                flush=True,
            )
    result = {
        "chosen": _summary(runs, "chosen"),
        "refined": _summary(runs, "refined"),
        "model": {"n_hypotheses": model.n_hypotheses, "refine_levels": model.refine_levels},
        "runs": runs,
    }
    text = json.dumps(result, indent=2)
    print(text)
    if args.out is not None:
        args.out.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
