"""The regional stage on held-out hippocampus subjects: shape-only, refined, and their ceiling.

Usage::

    python benchmarks/bench_boundary.py --out boundary.json [--data DIR] [--train 100]
        [--test 30] [--model MODEL] [--seed 0] [--jobs 2] [--conditions acquired,random]

Trains a model (labels 1+2, default settings, seeded) on ``--train`` hippocampus cases of
subjects that are not tested (``subjects.csv``; the split of ``bench_pose_study.py``), or
loads ``--model`` (written there after training, so a second run reuses it). Each of
``--test`` cases of other subjects is segmented once (no initialisation), and scored on:

* ``shape``: the template warped onto the landmarks found (``Segmentation.shape_label``);
* ``refined``: after the regional stage (``Segmentation.label``, the default output);
* ``ceiling_shape`` / ``ceiling_refined``: the same two from the case's *reference*
  landmarks (the template's landmarks carried onto its true label map with
  :func:`medseg.correspondence.transfer_landmarks`): what perfect landmarks would give.

Each case is also segmented under the named pose conditions of ``--conditions``
(:mod:`medseg.evaluation.perturbation`, case ``i`` seeded by ``--seed + i``; the ceiling
only as acquired), so that the regional stage's loss under pose can be set against the
shape-only one's. ``fixed_shape`` / ``fixed_refined`` hold the landmarks found on the
acquired image fixed: carried by each condition's transform onto the perturbed image, the
template is warped and the stage run from them, so that what the stage alone loses to
resampling is measured apart from what detection and the MRF lose (2026-12-06, 61 held-out
cases: the stage lost 0.007 more than the warp under the random similarity, and as much
under half a voxel of shift alone).

Per case, condition and map: Dice of the union and of each label, HD95 of the union (mm);
the regional stage's seconds and the quality score. One JSON file with the rows and a
printed summary per condition. Nothing is written into the repository.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from medseg.correspondence import transfer_landmarks
from medseg.datasets import load_cohort
from medseg.evaluation.metrics import dice_per_label, score_segmentation
from medseg.evaluation.perturbation import UNPERTURBED, perturb_condition
from medseg.io import label_values
from medseg.reconstruction import warp_labels

sys.path.insert(0, str(Path(__file__).parent))
from bench_pose_study import _default_data, _split, trained_model  # noqa: E402

LABELS = (1, 2)


def _scores(label: sitk.Image, truth: sitk.Image) -> dict:
    union = score_segmentation(label, truth)  # of the union
    per_label = dice_per_label(label, truth)
    return {"dice": union.dice, "hd95": union.hd95} | {f"dice{v}": per_label[v] for v in LABELS}


def _summary(rows: list[dict], condition: str) -> None:
    print(f"{condition}: {len(rows)} cases; mean Dice (label 1 / label 2), median HD95 mm")
    names = ("shape", "refined", "ceiling_shape", "ceiling_refined")
    for name in names if condition == UNPERTURBED else names[:2]:
        dice = [r[name]["dice"] for r in rows]
        print(
            f"  {name:16s} Dice {np.mean(dice):.3f} (median {np.median(dice):.3f}, min "
            f"{np.min(dice):.3f}; {np.mean([r[name]['dice1'] for r in rows]):.3f} / "
            f"{np.mean([r[name]['dice2'] for r in rows]):.3f}), HD95 "
            f"{np.median([r[name]['hd95'] for r in rows]):.2f}"
        )
    stage = [r["boundary_seconds"] for r in rows]
    print(f"  regional stage {np.median(stage):.2f} s a case (median; max {np.max(stage):.2f})")
    better = sum(r["refined"]["dice"] > r["shape"]["dice"] for r in rows)
    print(f"  refined better than shape-only on {better} of {len(rows)} cases")


def _fixed_losses(rows: list[dict], conditions: list[str]) -> None:
    """Each condition's Dice loss (acquired minus perturbed, paired by case) with the found
    landmarks held fixed: the warp's, the stage's, and the stage's beyond the warp's."""
    acquired = {r["case"]: r for r in rows if r["condition"] == UNPERTURBED}
    for condition in conditions:
        pairs = [(acquired[r["case"]], r) for r in rows if r["condition"] == condition]
        if condition == UNPERTURBED or not pairs:
            continue
        warp, stage = (
            np.array([a[name]["dice"] - r[name]["dice"] for a, r in pairs])
            for name in ("fixed_shape", "fixed_refined")
        )
        extra = stage - warp
        se = extra.std(ddof=1) / np.sqrt(len(extra)) if len(extra) > 1 else float("nan")
        print(
            f"{condition}, landmarks held fixed: Dice loss of the warp {warp.mean():+.4f}, of "
            f"the stage {stage.mean():+.4f}, the stage's beyond the warp's {extra.mean():+.4f}"
            f" (s.e. {se:.4f})"
        )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--data", type=Path, default=None)
    parser.add_argument("--train", type=int, default=100)
    parser.add_argument("--test", type=int, default=30)
    parser.add_argument("--model", type=Path, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--conditions", default=UNPERTURBED)
    args = parser.parse_args(argv)
    conditions = [c.strip() for c in args.conditions.split(",") if c.strip()]
    cohort = load_cohort(args.data or _default_data())
    train, test = _split(cohort, args.train, args.test, args.seed)
    model = trained_model(cohort, train, args.model, seed=args.seed, jobs=args.jobs)
    if model.boundary_ is None:
        raise SystemExit(f"{args.model} has no regional stage; train one with this medseg")
    model.n_jobs = model.detector_.n_jobs = args.jobs
    view = (model.frame_, model.template_mask_, model.template_landmarks_)
    stage = model.boundary_
    rows = []
    for i in test:
        case = cohort[i]
        acquired, labels = case.load_image(), label_values(case.load_label(), LABELS)
        first = model.segment(acquired)  # the acquired condition's, and the fixed landmarks
        for condition in conditions:
            image, truth, carried, _, _ = perturb_condition(
                condition, acquired, labels, first.landmarks, random_state=args.seed + i
            )
            seg = first if condition == UNPERTURBED else model.segment(image)
            row = {
                "case": case.case_id,
                "condition": condition,
                "shape": _scores(seg.shape_label, truth),
                "refined": _scores(seg.label, truth),
                "boundary_seconds": seg.timings["boundary"],
                "seconds": float(sum(seg.timings.values())),
                "quality": seg.quality,
                "fixed_shape": _scores(warp_labels(*view[1:], carried, image), truth),
                "fixed_refined": _scores(stage.refine(*view, image, carried).label, truth),
            }
            if condition == UNPERTURBED:
                reference = transfer_landmarks(
                    model.template_surface_,
                    model.template_landmarks_,
                    case.load_label(),
                    labels=LABELS,
                    keep_largest=True,
                    random_state=args.seed,
                )
                ceiling = model.boundary_.refine(*view, image, reference).label
                template = warp_labels(*view[1:], reference, image)
                row["ceiling_shape"] = _scores(template, truth)
                row["ceiling_refined"] = _scores(ceiling, truth)
            rows.append(row)
            print(case.case_id, condition, f"refined Dice {row['refined']['dice']:.3f}",
                  flush=True)  # fmt: skip
    args.out.write_text(json.dumps({"train": train, "test": test, "rows": rows}, indent=1))
    for condition in conditions:
        _summary([r for r in rows if r["condition"] == condition], condition)
    _fixed_losses(rows, conditions)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
