"""Where pose leaks in: the segmenter on real cases under controlled changes of pose and view.

Usage::

    python benchmarks/bench_pose_study.py --out study.jsonl [--data DIR] [--train 80]
        [--test 10] [--model MODEL] [--conditions acquired,pad_zeros,...]
        [--variants default,carried,...] [--seed 0]

Trains a model (labels 1+2, default settings, seeded) on ``--train`` hippocampus cases of
subjects that are not tested (``subjects.csv``), or loads ``--model`` (written there after
training, so a second run reuses it). Each of ``--test`` cases of other subjects is then
segmented under each condition, with no initialisation of any kind. The conditions are
those of ``medseg-evaluate --perturbation``, defined in one place,
:mod:`medseg.evaluation.perturbation` (``CONDITIONS``, ``perturb_condition``); the default
list is:

* ``acquired``: as it is;
* ``pad_zeros`` / ``pad_noise``: the same voxels in a field of view padded by 15 mm of zeros,
  or of noise with the mean and spread of the image's border voxels;
* ``rot45`` ... ``rot180``: a rotation about a random axis through the image centre (any
  ``rotN``, N in 0-180, is accepted);
* ``scale0.8`` ... ``scale1.25``: a scaling about the image centre (any ``scaleS``,
  0.5 < S < 2);
* ``random``: rotation of up to 45 degrees about a random axis and a scale in 0.8-1.25
  (log-uniform), the issue's protocol;

all but ``acquired`` and ``pad_*`` resampled onto the grid padded by 15 mm (zeros outside),
the label map with the same transform, and scored on it. Case ``i`` of the cohort is
perturbed with the seed ``--seed + i``. Each condition can be run with
stages swapped for their reference (``--variants``):

* ``default``: the model as trained;
* ``carried``: the candidates detected in the acquired image, moved by the same transform
  (the detectors taken out of the question);
* ``no_refine``: the MRF's landmarks, without the active-shape refinement;
* ``no_handedness``: the prior without the handedness term;
* ``scale_free``: the paper's prior (``invariant="distance"``) instead of the size-aware one;
* ``frame1``: one more pass in the shape's frame (``frame_passes=1``).

One JSON line per (case, condition, variant): Dice and HD95 of the union, landmark
disagreement with the acquired run (mm, mapped through the transform), seconds. The summary
(``--summary`` on an existing file) gives the mean Dice per condition and variant and its
loss against ``acquired``. Nothing is written into the repository.
"""

from __future__ import annotations

import argparse
import copy
import functools
import json
import sys
import time
from pathlib import Path

import numpy as np

from medseg.datasets import load_cohort
from medseg.detection import gradient_directions
from medseg.evaluation.metrics import dice, hd95
from medseg.evaluation.perturbation import (
    CONDITIONS,
    parse_condition,
    perturb_condition,
)
from medseg.io import select_labels
from medseg.segmenter import ShapePriorSegmenter, load_model
from medseg.shape import OrientationPrior, TripletPrior

LABELS = (1, 2)
VARIANTS = ("default", "carried", "no_refine", "no_handedness", "scale_free", "frame1")


def _default_data() -> Path:
    return Path(__file__).resolve().parents[2] / "shared" / "data" / "hippocampus"


def _split(cohort, n_train: int, n_test: int, seed: int):
    """Test cases of distinct subjects; training cases of the other subjects."""
    rng = np.random.default_rng(seed)
    subjects = np.unique(cohort.subjects)
    test_subjects = set(rng.permutation(subjects)[:n_test].tolist())
    test, train = [], []
    for i in range(len(cohort)):
        if cohort.subjects[i] in test_subjects:
            if not any(cohort.subjects[j] == cohort.subjects[i] for j in test):
                test.append(i)
        else:
            train.append(i)
    train = rng.permutation(train)[:n_train]
    return sorted(int(i) for i in train), test


def trained_model(cohort, train, path: Path | None, *, seed: int, jobs: int, **params):
    """The model saved at ``path`` when it holds one; else one trained (labels 1+2, seeded)
    on the cases ``train`` of ``cohort``, and saved at ``path`` when given."""
    if path is not None and (path / "model.json").is_file():
        return load_model(path)
    t0 = time.perf_counter()
    model = ShapePriorSegmenter(labels=LABELS, random_state=seed, n_jobs=jobs, **params)
    model.fit(cohort[train])
    print(f"trained on {len(train)} cases in {time.perf_counter() - t0:.0f} s", flush=True)
    if path is not None:
        model.save(path)
    return model


def _scale_free(model: ShapePriorSegmenter, cohort, train) -> ShapePriorSegmenter:
    """The same model with the paper's scale-free prior (and its handedness term refitted
    on the new cliques)."""
    from medseg.segmenter._estimator import _jittered  # the fit's own jitter

    other = copy.copy(model)
    rng = np.random.RandomState(0)
    shapes = _jittered(model.landmarks_, model.landmark_noise_mm, model.n_noise_copies, rng)
    other.prior_ = TripletPrior(
        cliques=model.cliques,
        density=model.density,
        invariant="distance",
        alpha=model.alpha,
        random_state=rng,
    ).fit(shapes)
    images = [cohort[i].load_image() for i in train if cohort[i].case_id in model.cases_]
    directions = np.stack([
        gradient_directions(im, pts, sigma_mm=model.orientation_sigma_mm)
        for im, pts in zip(images, model.landmarks_, strict=True)
    ])  # fmt: skip
    other.orientation_ = OrientationPrior().fit(
        model.landmarks_, directions, cliques=other.prior_.cliques_
    )
    other.invariant = "distance"
    return other


def _order(condition: str) -> tuple:
    """Table order: the default conditions first, as listed, then the others by name."""
    known = list(CONDITIONS)
    return (known.index(condition), "") if condition in known else (len(known), condition)


def _param(text: str) -> tuple[str, object]:
    """``NAME=VALUE`` of a model parameter; the value read as JSON when it parses."""
    name, _, value = text.partition("=")
    try:
        return name, json.loads(value)
    except json.JSONDecodeError:
        return name, value


def _summary(path: Path) -> None:
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    base = {(r["case"], r["variant"]): r["dice"] for r in rows if r["condition"] == "acquired"}
    base_default = {r["case"]: r["dice"] for r in rows if r["condition"] == "acquired"
                    and r["variant"] == "default"}  # fmt: skip
    table: dict = {}
    for r in rows:
        table.setdefault((r["condition"], r["variant"]), []).append(r)
    print(f"{'condition':<12}{'variant':<15}{'n':>3}{'Dice':>8}{'loss':>8}{'vs default':>11}"
          f"{'HD95':>7}{'agree mm':>10}")  # fmt: skip
    order = sorted(table, key=lambda cv: (_order(cv[0]), VARIANTS.index(cv[1])))
    for (cond, var), rs in ((key, table[key]) for key in order):
        d = np.array([r["dice"] for r in rs])
        same = [base.get((r["case"], var), np.nan) for r in rs]
        ref = [base_default.get(r["case"], np.nan) for r in rs]
        agree = [r["agreement_mm"] for r in rs if r["agreement_mm"] is not None]
        print(
            f"{cond:<12}{var:<15}{len(rs):>3}{d.mean():>8.3f}{np.nanmean(same) - d.mean():>8.3f}"
            f"{np.nanmean(ref) - d.mean():>11.3f}{np.median([r['hd95'] for r in rs]):>7.2f}"
            f"{(np.median(agree) if agree else np.nan):>10.2f}"
        )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=_default_data())
    parser.add_argument("--out", type=Path, required=True, help="JSON lines (appended).")
    parser.add_argument("--model", type=Path, default=None)
    parser.add_argument("--train", type=int, default=80)
    parser.add_argument("--test", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument(
        "--param", action="append", default=[], help="Model parameter NAME=VALUE (training)."
    )
    parser.add_argument(
        "--conditions",
        default=",".join(CONDITIONS),
        help="Comma-separated: acquired, pad_zeros, pad_noise, rotN (0-180), scaleS "
        "(0.5-2), random. Default: " + ",".join(CONDITIONS),
    )
    parser.add_argument("--variants", default="default")
    parser.add_argument("--summary", action="store_true", help="Summarise --out and stop.")
    args = parser.parse_args(argv)
    if args.summary:
        _summary(args.out)
        return 0
    variants = [v for v in args.variants.split(",") if v]
    for name in variants:
        if name not in VARIANTS:
            raise SystemExit(f"unknown variant {name!r}: choose among {', '.join(VARIANTS)}")
    try:  # canonical names (rot90.0 -> rot90), as the results file records them
        conditions = [parse_condition(c).name for c in args.conditions.split(",") if c]
    except ValueError as exc:  # medseg's ParameterError
        raise SystemExit(str(exc)) from None
    cohort = load_cohort(args.data)
    train, test = _split(cohort, args.train, args.test, args.seed)
    params = dict(_param(text) for text in args.param)
    model = trained_model(cohort, train, args.model, seed=args.seed, jobs=args.jobs, **params)
    models = {"default": model, "carried": model}
    if "no_refine" in variants:
        models["no_refine"] = copy.copy(model).set_params(refine_levels=0)
    if "no_handedness" in variants:
        models["no_handedness"] = copy.copy(model).set_params(orientation_weight=0.0)
    if "scale_free" in variants:
        models["scale_free"] = _scale_free(model, cohort, train)
    if "frame1" in variants:
        models["frame1"] = copy.copy(model).set_params(frame_passes=1)
    done = set()
    if args.out.is_file():
        for line in args.out.read_text().splitlines():
            r = json.loads(line)
            done.add((r["case"], r["condition"], r["variant"]))
    for i in test:
        case = cohort[i]
        image = case.load_image()
        label = select_labels(case.load_label(), LABELS)
        acquired = model.segment(image)
        for cond in conditions:
            moved, moved_label, _, change, centre = perturb_condition(
                cond, image, label, random_state=args.seed + i
            )
            for var in variants:
                if (case.case_id, cond, var) in done:
                    continue
                t0 = time.perf_counter()
                carried = var == "carried"
                move = functools.partial(change.apply, centre=centre)
                cands = acquired.candidates.mapped(move, moved) if carried else None
                try:
                    seg = models[var].segment(moved, candidates=cands)
                    score, dist = dice(seg.label, moved_label), hd95(seg.label, moved_label)
                    moved_truth = change.apply(acquired.landmarks, centre)
                    agree = float(np.median(np.linalg.norm(moved_truth - seg.landmarks, axis=1)))
                except Exception as exc:  # a failed case scores 0, as in the evaluation
                    print(f"{case.case_id} {cond} {var}: {exc}", file=sys.stderr)
                    score, dist, agree = 0.0, float("inf"), None
                row = {
                    "case": case.case_id, "condition": cond, "variant": var, "dice": score,
                    "hd95": dist, "agreement_mm": agree, "angle": change.angle_deg,
                    "scale": change.scale, "seconds": time.perf_counter() - t0,
                }  # fmt: skip
                with open(args.out, "a") as fh:
                    fh.write(json.dumps(row) + "\n")
                print(json.dumps(row), flush=True)
    _summary(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
