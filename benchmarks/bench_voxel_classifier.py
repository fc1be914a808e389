"""Which voxel classifier the regional stage should use: accuracy per second, side by side.

Usage::

    python benchmarks/bench_voxel_classifier.py --out voxel.json [--data DIR] [--train 100]
        [--test 20] [--seed 0] [--jobs 2] [--methods rf30,rf30_ms0.5,hgb100,...]

Builds the regional stage's training cases once (:meth:`BoundaryStage._training_case`:
each image resampled into the shape's frame of its reference landmarks jittered by the
stage's ``jitter_mm``, its features on the band and the true labels there) for ``--train``
hippocampus cases and ``--test`` cases of other subjects (the split of
``bench_pose_study.py``; reference landmarks from
:func:`medseg.correspondence.landmarks_from_labels` on all of them, labels 1 and 2). Each
method is fitted on the training cases' rows (``rows_per_case`` of each, as the stage draws
them; no auto-context, the same rows for every method) and scored on the test cases:

* fit seconds, predict milliseconds per case (median), held-out log-loss;
* Dice (mean over labels 1 and 2) after the stage's graph cut, per pair of cut weights in
  ``PAIRS``, and the paired difference to the first method with its standard error.

The figures are about the choice between classifiers, not the stage's absolute Dice (no
auto-context, jittered reference landmarks instead of found ones). One JSON file and a
printed table. Nothing is written into the repository.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from itertools import product
from pathlib import Path

import numpy as np
from sklearn.ensemble import (
    ExtraTreesClassifier,
    HistGradientBoostingClassifier,
    RandomForestClassifier,
)
from sklearn.metrics import log_loss

from medseg.correspondence import landmarks_from_labels
from medseg.datasets import load_cohort
from medseg.frame import ShapeFrame
from medseg.io import label_values, select_labels
from medseg.segmenter._boundary import BoundaryStage, _cut, _dice_scores

sys.path.insert(0, str(Path(__file__).parent))
from bench_pose_study import _default_data, _split  # noqa: E402  (the same split)

LABELS = (1, 2)
PAIRS = tuple(product((0.5, 1.0), (0.1, 0.3)))  # (smoothness, shape_weight) of the cut


def _methods(jobs: int, seed: int) -> dict:
    def forest(n, **kw):
        return lambda: RandomForestClassifier(
            n, min_samples_leaf=5, max_features="sqrt", n_jobs=jobs, random_state=seed, **kw
        )

    def boosting(n, rate, leaves=31):
        return lambda: HistGradientBoostingClassifier(
            max_iter=n,
            learning_rate=rate,
            max_leaf_nodes=leaves,
            early_stopping=False,
            random_state=seed,
        )

    return {
        "rf30": forest(30),  # the stage's classifier today
        "rf30_ms0.5": forest(30, max_samples=0.5),
        "rf30_ms0.3": forest(30, max_samples=0.3),
        "rf15": forest(15),
        "et30": lambda: ExtraTreesClassifier(
            30, min_samples_leaf=5, max_features="sqrt", n_jobs=jobs, random_state=seed
        ),
        "hgb50": boosting(50, 0.2),
        "hgb100": boosting(100, 0.1),
    }


def _cases(cohort, indices, seed: int, jobs: int) -> list:
    """The stage's training cases (view, truth, nodes, features) of ``indices``."""
    images = [cohort[i].load_image() for i in indices]
    labels = [cohort[i].load_label() for i in indices]
    masks = [select_labels(label, LABELS) for label in labels]
    maps = [label_values(label, LABELS) for label in labels]
    corr = landmarks_from_labels(masks, labels=(1,), random_state=seed, n_jobs=jobs)
    points = np.asarray(corr.landmarks)
    keep = ~np.asarray(corr.failed)
    ref = int(corr.reference_index)
    frame = ShapeFrame.fit(points[keep], [im for im, k in zip(images, keep, strict=True) if k])
    stage = BoundaryStage(random_state=seed)
    stage.atlases_ = None
    rng = np.random.RandomState(seed)
    template = (frame, maps[ref], points[ref])
    return [
        stage._training_case(*template, images[i], maps[i], points[i], rng, None)
        if keep[i]
        else None
        for i in range(len(indices))
    ]


def _evaluate(classifier, cases) -> dict:
    stage = BoundaryStage()
    stage.values_ = LABELS
    predict_s, losses, dices = [], [], {pair: [] for pair in PAIRS}
    for view, truth, nodes, features in cases:
        t0 = time.perf_counter()
        probabilities = stage._probabilities(classifier, features)
        predict_s.append(time.perf_counter() - t0)
        losses.append(log_loss(truth[nodes], np.clip(probabilities, 1e-6, 1), labels=[0, 1, 2]))
        for smooth, weight in PAIRS:
            cut = _cut(
                view,
                probabilities,
                nodes,
                band_mm=stage.band_mm,
                smoothness=smooth,
                shape_weight=weight,
            )
            dices[(smooth, weight)].append(_dice_scores(cut, truth, view.values))
    return {
        "predict_ms": 1000 * float(np.median(predict_s)),
        "log_loss": float(np.mean(losses)),
        "dice": {f"{s},{w}": [float(v) for v in d] for (s, w), d in dices.items()},
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--data", type=Path, default=_default_data())
    parser.add_argument("--train", type=int, default=100)
    parser.add_argument("--test", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--methods", default="rf30,rf30_ms0.5,rf30_ms0.3,rf15,et30,hgb50,hgb100")
    args = parser.parse_args(argv)
    warnings.filterwarnings("ignore", category=UserWarning)  # feature names of the rows
    methods = _methods(args.jobs, args.seed)
    names = args.methods.split(",")
    unknown = sorted(set(names) - set(methods))
    if unknown:
        parser.error(f"unknown method(s) {unknown}; known: {sorted(methods)}")
    cohort = load_cohort(args.data)
    train, test = _split(cohort, args.train, args.test, args.seed)
    cases = _cases(cohort, train + test, args.seed, args.jobs)
    train_cases = [c for c in cases[: len(train)] if c is not None]
    test_cases = [c for c in cases[len(train) :] if c is not None]
    # the rows as the stage draws them (``rows_per_case`` of each case)
    rng = np.random.RandomState(args.seed)
    X, y = BoundaryStage()._rows(train_cases, range(len(train_cases)), rng)
    print(f"{len(train_cases)} training cases ({len(X)} rows), {len(test_cases)} test cases")
    results = {}
    for name in names:
        t0 = time.perf_counter()
        classifier = methods[name]().fit(X, y)
        fit_s = time.perf_counter() - t0
        results[name] = {"fit_s": fit_s} | _evaluate(classifier, test_cases)
    first = names[0]
    print(
        f"{'method':12s} {'fit s':>7s} {'ms/case':>8s} {'log-loss':>9s}  Dice per cut pair "
        f"(paired difference to {first} +- s.e.)"
    )
    for name, r in results.items():
        cells = []
        for pair, values in r["dice"].items():
            diff = np.asarray(values) - np.asarray(results[first]["dice"][pair])
            sem = diff.std(ddof=1) / np.sqrt(len(diff)) if len(diff) > 1 else float("nan")
            cells.append(f"{pair}: {np.mean(values):.4f} ({diff.mean():+.4f}+-{sem:.4f})")
        print(
            f"{name:12s} {r['fit_s']:7.1f} {r['predict_ms']:8.1f} {r['log_loss']:9.4f}  "
            + "  ".join(cells)
        )
    args.out.write_text(
        json.dumps(
            {
                "args": vars(args) | {"data": str(args.data), "out": str(args.out)},
                "results": results,
            },
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
