"""One fold's work: fit every method on the training cases, segment and score the test cases.

A :class:`FoldTask` holds everything one fold needs and is picklable, so that
:func:`run_fold` runs the same in this process, in a joblib worker or on a Dask worker
(:mod:`medseg.evaluation.runner` hands them out). For each test case, and each of its
pose-perturbed copies, every method variant listed in the task's ``todo`` is segmented and
scored (:data:`medseg.evaluation.results.SCORES`: Dice, HD95, ASSD, landmark error, duality
gap); the unperturbed predictions can be written for the report. A method that raises a
:class:`~medseg.errors.MedsegError` on a case is scored as a failure and the fold goes on.
"""

from __future__ import annotations

import inspect
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from medseg.errors import MedsegError
from medseg.evaluation.methods import MethodSpec
from medseg.evaluation.metrics import landmark_errors, score_segmentation
from medseg.evaluation.perturbation import perturb_case, random_similarity
from medseg.evaluation.references import fold_landmarks
from medseg.evaluation.results import prediction_path, result_key
from medseg.io import read_image, select_labels, write_image

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
    angles: tuple[float, ...]
    todo: frozenset
    predictions_dir: str | None = None


# A method that raised MedsegError on a case: no overlap, no surface, no landmarks. The
# summary counts the non-finite values (shown as ``finite/total``), so failures stay visible.
_FAILED = {
    "dice": 0.0,
    "hd95": math.inf,
    "assd": math.inf,
    "landmark_error_mm": math.nan,
    "landmark_error_vox": math.nan,
    "gap": math.nan,
}


def _perturbation_seed(seed: int, case_id: str, angle: float) -> int:
    key = [int(seed), 7919, int(round(angle * 1000))] + [ord(ch) for ch in case_id]
    return int(np.random.SeedSequence(key).generate_state(1)[0])


def _score(result, mask, reference_landmarks, image) -> dict:
    label = read_image(result.label)
    scores = score_segmentation(label, mask)
    est = np.asarray(result.landmarks, dtype=float)
    if reference_landmarks is not None and est.shape == np.shape(reference_landmarks):
        mm, vox = landmark_errors(est, reference_landmarks, image)
        lm_mm, lm_vox = float(mm.mean()), float(vox.mean())
    else:
        lm_mm = lm_vox = math.nan
    mrf = getattr(result, "mrf", None)
    gap = float(mrf.gap) if mrf is not None and getattr(mrf, "gap", None) is not None else math.nan
    return {
        "dice": scores.dice,
        "hd95": scores.hd95,
        "assd": scores.assd,
        "landmark_error_mm": lm_mm,
        "landmark_error_vox": lm_vox,
        "gap": gap,
    }


def _save_prediction(result, image, folder: Path, method: str, case_id: str) -> None:
    path = prediction_path(folder, method, case_id)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(read_image(result.label), path, like=image)


def _test_inputs(task: FoldTask, references) -> list[tuple]:
    """The test inputs, original and perturbed, shared by all methods.

    One ``(case, angle, scale, image, mask, reference_landmarks)`` per test case and angle.
    """
    inputs = []
    for case, ref_lm in zip(task.test, references, strict=True):
        image = case.load_image()
        mask = select_labels(case.load_label(), task.labels)
        for angle in task.angles:
            if angle == 0:
                inputs.append((case, angle, 1.0, image, mask, ref_lm))
                continue
            change = random_similarity(
                angle, random_state=_perturbation_seed(task.run_seed, case.case_id, angle)
            )
            moved = perturb_case(image, mask, ref_lm, change)
            inputs.append((case, angle, change.scale) + moved)
    return inputs


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
        One per (method, test case, perturbation angle) listed in ``task.todo``, with the
        columns :data:`medseg.evaluation.results.COLUMNS`.
    """
    rows: list[dict] = []
    train, references = fold_landmarks(
        task.train, task.test, labels=task.labels, n_landmarks=task.n_landmarks, seed=task.seed
    )
    inputs = _test_inputs(task, references)
    for spec in task.specs:
        wanted = [
            (name, kwargs, item)
            for item in inputs
            for name, kwargs in spec.variants.items()
            if result_key(name, task.fold, item[0].case_id, item[1]) in task.todo
        ]
        if not wanted:
            continue
        t0 = time.perf_counter()
        estimator = spec.build(task.seed).fit(train)
        fit_seconds = time.perf_counter() - t0
        # Variants of one estimator on one input share its detection (e.g. the shape prior
        # and detection-only): the candidates are computed once, their time counted in both.
        shares = "candidates" in inspect.signature(estimator.segment).parameters
        detected: dict[int, tuple] = {}
        for name, kwargs, item in wanted:
            case, angle, scale, image, mask, ref_lm = item
            extra, reused = {}, 0.0
            if shares and id(item) in detected:
                extra["candidates"], reused = detected[id(item)]
            t0 = time.perf_counter()
            try:
                result = estimator.segment(image, **kwargs, **extra)
            except MedsegError as exc:  # one failed case is a result, not the end of the run
                print(
                    f"{name} failed on {case.case_id} ({angle:g} degrees), scored as Dice 0: {exc}",
                    file=sys.stderr,
                )
                result = None
            seconds = time.perf_counter() - t0 + reused
            if shares and id(item) not in detected and hasattr(result, "candidates"):
                detected[id(item)] = (result.candidates, result.timings.get("detection", 0.0))
            row = {
                "method": name,
                "fold": task.fold,
                "case": case.case_id,
                "subject": str(case.subject),
                "perturbation_deg": float(angle),
                "scale": float(scale),
                **(_FAILED if result is None else _score(result, mask, ref_lm, image)),
                "seconds": seconds,
                "fit_seconds": fit_seconds,
            }
            if result is not None and task.predictions_dir is not None and angle == 0:
                _save_prediction(result, image, Path(task.predictions_dir), name, case.case_id)
            rows.append(row)
            if on_row is not None:
                on_row(row)
    return rows
