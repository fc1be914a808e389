"""One fold's work: fit every method on the training cases, segment and score the test cases.

A :class:`FoldTask` holds everything one fold needs and is picklable, so that
:func:`run_fold` runs the same in this process, in a joblib worker or on a Dask worker
(:mod:`medseg.evaluation.runner` hands them out). For each test case, and each of its
pose-perturbed copies (one per named condition of
:func:`medseg.evaluation.perturbation.perturb_condition`, seeded by the run's seed, the case
and the condition), every method variant listed in the task's ``todo`` is segmented and
scored on the perturbed grid (:data:`medseg.evaluation.results.SCORES`: Dice, HD95, ASSD,
landmark error, duality gap); the unperturbed predictions can be written for the report. A
method that raises a :class:`~medseg.errors.MedsegError` on a case is scored as a failure
and the fold goes on; a method without landmarks (``result.landmarks is None``, e.g. the
multi-atlas baseline) gets NaN landmark errors.

With ``models_dir``, an estimator that can be saved (``save(folder)`` and a class method
``load(folder)``, as the shape-prior segmenter) is written there once fitted, and a later
run (a resume, or more conditions or methods on the same folder) loads it instead of
fitting again, if it was fitted on the same training cases, with the same parameters and
seed, by the same source code of medseg (:func:`_code_digest`); otherwise it is refitted
and replaced. A fold's fit is the larger part of its work on the hippocampus (about 20 of
35 minutes for the segmenter in a 5-fold run with one perturbation).
"""

from __future__ import annotations

import copy as _copy
import functools
import hashlib
import inspect
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from medseg.errors import MedsegError
from medseg.evaluation.methods import MethodSpec
from medseg.evaluation.metrics import dice_per_label, landmark_errors, score_segmentation
from medseg.evaluation.perturbation import UNPERTURBED, perturb_condition
from medseg.evaluation.references import fold_landmarks
from medseg.evaluation.results import prediction_path, result_key
from medseg.io import atomic_folder, label_values, read_image, write_image

__all__ = ["FoldTask", "run_fold"]


@dataclass(frozen=True)
class FoldTask:
    """Everything one fold needs; picklable, so it can run in another process or host."""

    fold: int
    train: object  # Cohort
    test: object  # Cohort
    seed: int
    run_seed: int
    specs: tuple[MethodSpec, ...]
    labels: tuple[int, ...]
    n_landmarks: int | None
    conditions: tuple[str, ...]  # canonical names, "acquired" first (check_conditions)
    todo: frozenset
    predictions_dir: str | None = None
    models_dir: str | None = None  # fitted estimators kept there and reused (see above)


# A method that raised MedsegError on a case: no overlap, no surface, no landmarks. The
# summary counts the non-finite values (shown as ``finite/total``), so failures stay visible.
_FAILED = {
    "dice": 0.0,
    "hd95": math.inf,
    "assd": math.inf,
    "landmark_error_mm": math.nan,
    "landmark_error_vox": math.nan,
    "gap": math.nan,
    "dice_by_label": "",
    "quality": math.nan,
}


def _perturbation_seed(seed: int, case_id: str, condition: str) -> int:
    """The seed of one perturbed copy: a function of the run's seed, the case and the
    condition only (not of the fold, the method or the order of work)."""
    key = [int(seed), 7919, *(ord(ch) for ch in condition), 0, *(ord(ch) for ch in case_id)]
    return int(np.random.SeedSequence(key).generate_state(1)[0])


def _dice_by_label(label: sitk.Image, reference: sitk.Image) -> str:
    """``"1:0.8912;2:0.8801"``: the Dice of each value of a reference of several labels."""
    scores = dice_per_label(label, reference)
    return ";".join(f"{v}:{d:.6f}" for v, d in scores.items()) if len(scores) > 1 else ""


def _relabelled(result, attribute: str):
    """A shallow copy of ``result`` whose ``label`` is its ``attribute`` (None if absent)."""
    label = None if result is None else getattr(result, attribute, None)
    if label is None:
        return None
    out = _copy.copy(result)
    out.label = label
    return out


def _score(result, labels, reference_landmarks, image) -> dict:
    label = read_image(result.label)
    scores = score_segmentation(label, labels)  # of the union: it binarises both
    est = None if result.landmarks is None else np.asarray(result.landmarks, dtype=float)
    if (
        est is not None
        and reference_landmarks is not None
        and est.shape == np.shape(reference_landmarks)
    ):
        mm, vox = landmark_errors(est, reference_landmarks, image)
        lm_mm, lm_vox = float(mm.mean()), float(vox.mean())
    else:
        lm_mm = lm_vox = math.nan
    mrf = getattr(result, "mrf", None)
    gap = float(mrf.gap) if mrf is not None and getattr(mrf, "gap", None) is not None else math.nan
    quality = (getattr(result, "quality", None) or {}).get("score")
    return {
        "dice": scores.dice,
        "hd95": scores.hd95,
        "assd": scores.assd,
        "landmark_error_mm": lm_mm,
        "landmark_error_vox": lm_vox,
        "gap": gap,
        "dice_by_label": _dice_by_label(label, labels),
        "quality": math.nan if quality is None else float(quality),
    }


def _save_prediction(result, image, folder: Path, method: str, case_id: str) -> None:
    path = prediction_path(folder, method, case_id)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(read_image(result.label), path, like=image)


def _test_inputs(task: FoldTask, references) -> list[tuple]:
    """The test inputs, original and perturbed, shared by all methods.

    One ``(case, condition, change, image, labels, reference_landmarks)`` per test case and
    condition that some method still needs (``labels``: the values of ``task.labels``,
    :func:`medseg.io.label_values`).
    """
    needed = {(key[2], key[3]) for key in task.todo}
    inputs = []
    for case, ref_lm in zip(task.test, references, strict=True):
        if not any((case.case_id, c) in needed for c in task.conditions):
            continue
        image = case.load_image()
        labels = label_values(case.load_label(), task.labels)
        for condition in task.conditions:
            if (case.case_id, condition) not in needed:
                continue
            seed = _perturbation_seed(task.run_seed, case.case_id, condition)
            moved, moved_labels, moved_lm, change, _ = perturb_condition(
                condition, image, labels, ref_lm, random_state=seed
            )
            inputs.append((case, condition, change, moved, moved_labels, moved_lm))
    return inputs


@functools.cache
def _code_digest() -> str:
    """SHA-256 of the source files of medseg and of its evaluation (baselines included): a
    model cached by other code is not reused."""
    import medseg
    import medseg.evaluation

    digest = hashlib.sha256()
    for package in (medseg, medseg.evaluation):
        root = Path(package.__file__).parent
        for path in sorted(root.rglob("*.py")):
            digest.update(path.relative_to(root).as_posix().encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


def _fitted(spec: MethodSpec, task: FoldTask, train) -> tuple[object, float]:
    """The spec's estimator fitted on ``train``, and the seconds its fit took: loaded from
    ``task.models_dir`` when a matching one is there, else fitted (and kept there)."""
    estimator = spec.build(task.seed)
    cls = type(estimator)
    if task.models_dir is None or not (hasattr(cls, "load") and hasattr(estimator, "save")):
        t0 = time.perf_counter()
        return estimator.fit(train), time.perf_counter() - t0
    folder = Path(task.models_dir) / f"fold{task.fold}_{next(iter(spec.variants))}"
    key = {
        "estimator": f"{cls.__module__}.{cls.__qualname__}",
        "params": repr(sorted(spec.params.items())),
        "seed": int(task.seed),
        "labels": list(task.labels),
        "n_landmarks": task.n_landmarks,
        "train": list(train.case_ids),
        "code": _code_digest(),
    }
    try:
        kept = json.loads((folder / "fit.json").read_text(encoding="utf-8"))
        if {k: kept.get(k) for k in key} == key:
            return cls.load(folder / "model"), float(kept["fit_seconds"])
    except (OSError, ValueError, KeyError, MedsegError):
        pass  # none, another fit's, or unreadable: fit again
    t0 = time.perf_counter()
    estimator.fit(train)
    fit_seconds = time.perf_counter() - t0
    with atomic_folder(folder) as staging:
        estimator.save(staging / "model")
        record = json.dumps(key | {"fit_seconds": fit_seconds}, indent=1)
        (staging / "fit.json").write_text(record, encoding="utf-8")
    return estimator, fit_seconds


def run_fold(task: FoldTask, on_row: Callable[[dict], None] | None = None) -> list[dict]:
    """Fit every method on the fold's training cases and score its test cases.

    Parameters
    ----------
    task : FoldTask
    on_row : callable, optional
        Called with each row as soon as it is computed (the serial runner appends it to
        the CSV there).

    Returns
    -------
    rows : list of dict
        One per (method, test case, perturbation condition) listed in ``task.todo``, with
        the columns :data:`medseg.evaluation.results.COLUMNS`.
    """
    rows: list[dict] = []
    train, references = fold_landmarks(
        task.train, task.test, labels=task.labels, n_landmarks=task.n_landmarks, seed=task.seed
    )
    inputs = _test_inputs(task, references)
    for spec in task.specs:

        def todo(name, item):
            return result_key(name, task.fold, item[0].case_id, item[1]) in task.todo

        wanted = [
            (name, kwargs, item)
            for item in inputs
            for name, kwargs in spec.variants.items()
            if todo(name, item)
            or any(todo(d, item) for d in (*spec.derived_from(name), *spec.oracles_from(name)))
        ]
        if not wanted:
            continue
        estimator, fit_seconds = _fitted(spec, task, train)
        # Variants of one estimator on one input share its detection (e.g. the shape prior
        # and detection-only): the candidates are computed once, their time counted in both.
        shares = "candidates" in inspect.signature(estimator.segment).parameters
        detected: dict[int, tuple] = {}
        for name, kwargs, item in wanted:
            case, condition, change, image, labels, ref_lm = item
            extra, reused = {}, 0.0
            if shares and id(item) in detected:
                extra["candidates"], reused = detected[id(item)]
            # Oracles need only the fitted estimator: the variant is segmented when it, or a
            # method derived from its result, is still to score.
            segment = todo(name, item) or any(todo(d, item) for d in spec.derived_from(name))
            t0 = time.perf_counter()
            result = None
            try:
                if segment:
                    result = estimator.segment(image, **kwargs, **extra)
            except MedsegError as exc:  # one failed case is a result, not the end of the run
                print(
                    f"{name} failed on {case.case_id} ({condition}), scored as Dice 0: {exc}",
                    file=sys.stderr,
                )
            seconds = time.perf_counter() - t0 + reused
            if shares and id(item) not in detected and hasattr(result, "candidates"):
                detected[id(item)] = (result.candidates, result.timings.get("detection", 0.0))
            outputs = [(name, result, seconds)] if todo(name, item) else []
            for derived, attribute in spec.derived_from(name).items():
                if todo(derived, item):
                    outputs.append((derived, _relabelled(result, attribute), seconds))
            for oracle, function in spec.oracles_from(name).items():
                if todo(oracle, item):
                    t0 = time.perf_counter()
                    output = function(estimator, image, ref_lm)
                    if output is not None:  # no reference to score against: no row
                        outputs.append((oracle, output, time.perf_counter() - t0))
            for method, output, method_seconds in outputs:
                row = {
                    "method": method,
                    "fold": task.fold,
                    "case": case.case_id,
                    "subject": str(case.subject),
                    "perturbation": condition,
                    "perturbation_deg": float(change.angle_deg),
                    "scale": float(change.scale),
                    **(_FAILED if output is None else _score(output, labels, ref_lm, image)),
                    "seconds": method_seconds,
                    "fit_seconds": fit_seconds,
                }
                if (
                    output is not None
                    and task.predictions_dir is not None
                    and condition == UNPERTURBED
                ):
                    folder = Path(task.predictions_dir)
                    _save_prediction(output, image, folder, method, case.case_id)
                rows.append(row)
                if on_row is not None:
                    on_row(row)
    return rows
