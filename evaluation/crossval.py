"""Cross-validation by subject: folds, the fold runner, resumable per-case results.

* :func:`make_folds`: leave-one-subject-out (``"loo"``) or k-fold grouped by subject
  (scikit-learn's ``LeaveOneGroupOut`` / ``GroupKFold`` on ``cohort.subjects``): the cases
  of one person are never split between training and test;
* :func:`check_cohort`: the checks that run before any work (empty cohort, one subject,
  labels no case contains, folds too small to train on);
* :func:`run_folds`: fits every method once per fold, segments the fold's test cases (and
  their pose-perturbed copies), scores them, and appends one CSV row per (method, case,
  perturbation) as it finishes. A rerun on the same folder skips the rows already there.
  Folds run serially, on local cores (joblib, ``n_jobs``), or on an existing Dask cluster
  (``scheduler="tcp://host:port"``). Every fold's seed derives from ``seed`` and the fold
  number only, so the numbers do not depend on where or in which order folds run.
"""

from __future__ import annotations

import csv
import inspect
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from medseg.evaluation.methods import MethodSpec
from medseg.evaluation.metrics import landmark_errors, score_segmentation
from medseg.evaluation.perturbation import perturb_case, random_similarity
from medseg.evaluation.references import fold_landmarks
from sklearn.model_selection import GroupKFold, LeaveOneGroupOut
from tqdm.auto import tqdm

from medseg.errors import CohortError, LabelError, MedsegError
from medseg.io import atomic_write, read_image, select_labels, write_image
from medseg.segmenter import MIN_TRAINING_CASES

__all__ = [
    "COLUMNS",
    "MIN_TRAINING_CASES",
    "make_folds",
    "check_cohort",
    "run_folds",
    "read_results",
    "fold_seed",
    "prediction_path",
]

#: Columns of the per-case CSV, in order.
COLUMNS = (
    "method",
    "fold",
    "case",
    "subject",
    "perturbation_deg",
    "scale",
    "dice",
    "hd95",
    "assd",
    "landmark_error_mm",
    "landmark_error_vox",
    "gap",
    "seconds",
    "fit_seconds",
)
_FLOAT_COLUMNS = COLUMNS[4:]

#: How long to wait for a Dask scheduler before giving up.
DASK_CONNECT_TIMEOUT = "20s"


# ----------------------------------------------------------------------------- folds


def make_folds(cohort, folds: str | int = "loo") -> list[tuple[np.ndarray, np.ndarray]]:
    """Train / test case positions per fold, grouped by subject.

    Parameters
    ----------
    cohort : Cohort
    folds : "loo" or int
        "loo": one fold per subject (its cases are the test set); int k >= 2: k folds of
        ``GroupKFold`` (deterministic, balanced by case count).

    Returns
    -------
    folds : list of ((n_train,) int array, (n_test,) int array)
    """
    groups = np.asarray(cohort.subjects)
    n_subjects = len(set(groups.tolist()))
    index = np.zeros((len(groups), 1))
    if isinstance(folds, str):
        if folds != "loo":
            raise MedsegError(f"`folds` must be 'loo' or an integer >= 2, got {folds!r}")
        splitter = LeaveOneGroupOut()
    else:
        if isinstance(folds, bool) or not isinstance(folds, int | np.integer) or folds < 2:
            raise MedsegError(f"`folds` must be 'loo' or an integer >= 2, got {folds!r}")
        if folds > n_subjects:
            raise CohortError(
                f"{folds} folds asked but cohort {cohort.name!r} has only {n_subjects} "
                f"subjects; use at most {n_subjects} folds or 'loo'"
            )
        splitter = GroupKFold(n_splits=int(folds))
    return [(tr, te) for tr, te in splitter.split(index, groups=groups)]


def fold_seed(seed: int, fold: int) -> int:
    """The seed of one fold: a function of the run's seed and the fold number only."""
    return int(np.random.SeedSequence([int(seed), int(fold)]).generate_state(1)[0])


def _perturbation_seed(seed: int, case_id: str, angle: float) -> int:
    key = [int(seed), 7919, int(round(angle * 1000))] + [ord(ch) for ch in case_id]
    return int(np.random.SeedSequence(key).generate_state(1)[0])


def check_cohort(
    cohort,
    *,
    labels: Sequence[int],
    folds: str | int = "loo",
    progress: bool = False,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Validate a cohort for cross-validation before any work; return the folds.

    Raises
    ------
    CohortError
        Empty cohort, a single subject, more folds than subjects, a fold whose training set
        is smaller than :data:`MIN_TRAINING_CASES`, or a case without a label map.
    LabelError
        A requested label that no case contains, or a case that contains none of them.
    """
    name = getattr(cohort, "name", "cohort")
    if len(cohort) == 0:
        raise CohortError(
            f"cohort {name!r} is empty: point to a folder with imagesTr/ and labelsTr/ or a "
            "manifest listing cases"
        )
    n_subjects = len(set(np.asarray(cohort.subjects).tolist()))
    if n_subjects < 2:
        raise CohortError(
            f"cohort {name!r} has {len(cohort)} case(s) from a single subject: "
            "cross-validation by subject needs at least 2 subjects (check subjects.csv or "
            "the manifest's subject column)"
        )
    labels = tuple(int(v) for v in labels)
    if not labels or min(labels) < 1:
        raise LabelError(f"`labels` must be positive label values, got {labels}")
    found: set[int] = set()
    without = []
    for case in tqdm(cohort, desc="checking labels", disable=not progress, leave=False):
        if case.label is None:
            raise CohortError(f"case {case.case_id!r} has no label map: evaluation needs one")
        values = set(np.unique(_label_array(case)).tolist())
        found |= values
        if not values & set(labels):
            without.append(case.case_id)
    missing = [v for v in labels if v not in found]
    if missing:
        raise LabelError(
            f"label(s) {missing} occur in no case of cohort {name!r}; labels present: "
            f"{sorted(v for v in found if v)}; choose them with labels= "
            "(--label on the command line)"
        )
    if without:
        raise LabelError(
            f"{len(without)} case(s) contain none of the labels {list(labels)}: "
            f"{', '.join(without[:5])}{' ...' if len(without) > 5 else ''}"
        )
    splits = make_folds(cohort, folds)
    smallest = min(len(tr) for tr, _ in splits)
    if smallest < MIN_TRAINING_CASES:
        raise CohortError(
            f"a fold of cohort {name!r} would train on {smallest} case(s); at least "
            f"{MIN_TRAINING_CASES} are needed: add subjects or use fewer folds"
        )
    return splits


def _label_array(case) -> np.ndarray:
    import SimpleITK as sitk

    # a copy: a view of the temporary image returned by load_label would dangle
    return sitk.GetArrayFromImage(case.load_label())


# ----------------------------------------------------------------------------- CSV


def _format(value) -> str:
    if isinstance(value, float | np.floating):
        return repr(float(value))
    return str(value)


def _parse(row: dict) -> dict | None:
    if set(COLUMNS) - set(row) or any(row[c] is None for c in COLUMNS):
        return None
    try:
        out = {c: row[c] for c in COLUMNS}
        out["fold"] = int(row["fold"])
        for c in _FLOAT_COLUMNS:
            out[c] = float(row[c])
    except (TypeError, ValueError):
        return None
    return out


def read_results(path: str | os.PathLike) -> list[dict]:
    """Rows of a per-case CSV written by :func:`run_folds` (typed; torn lines dropped)."""
    path = Path(path)
    if not path.is_file():
        return []
    with path.open(newline="", encoding="utf-8") as fh:
        rows = [_parse(r) for r in csv.DictReader(fh)]
    return [r for r in rows if r is not None]


def _key(method: str, fold: int, case: str, angle: float) -> tuple:
    return (str(method), int(fold), str(case), round(float(angle), 6))


def _row_key(row: dict) -> tuple:
    return _key(row["method"], row["fold"], row["case"], row["perturbation_deg"])


class _ResultsFile:
    """The per-case CSV: rewritten clean on open (drops a torn last line), then appended."""

    def __init__(self, path: Path):
        self.path = path
        rows = read_results(path)
        with atomic_write(path) as tmp:
            with tmp.open("w", newline="", encoding="utf-8") as fh:
                writer = csv.DictWriter(fh, fieldnames=COLUMNS)
                writer.writeheader()
                for r in rows:
                    writer.writerow({c: _format(r[c]) for c in COLUMNS})
        self.done = {_row_key(r) for r in rows}

    def append(self, row: dict) -> None:
        with self.path.open("a", newline="", encoding="utf-8") as fh:
            csv.DictWriter(fh, fieldnames=COLUMNS).writerow({c: _format(row[c]) for c in COLUMNS})
            fh.flush()
            os.fsync(fh.fileno())
        self.done.add(_row_key(row))


# ----------------------------------------------------------------------------- one fold


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


def prediction_path(folder: str | os.PathLike, method: str, case_id: str) -> Path:
    """Where the label map predicted by ``method`` for ``case_id`` is written."""
    return Path(folder) / method / f"{case_id}.nii.gz"


def _save_prediction(result, image, folder: Path, method: str, case_id: str) -> None:
    path = prediction_path(folder, method, case_id)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(read_image(result.label), path, like=image)


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
        One per (method, test case, perturbation angle) listed in ``task.todo``.
    """
    rows: list[dict] = []
    train, references = fold_landmarks(
        task.train, task.test, labels=task.labels, n_landmarks=task.n_landmarks, seed=task.seed
    )
    # The test inputs, original and perturbed, shared by all methods.
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
    for spec in task.specs:
        wanted = [
            (name, kwargs, item)
            for item in inputs
            for name, kwargs in spec.variants.items()
            if _key(name, task.fold, item[0].case_id, item[1]) in task.todo
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


# ----------------------------------------------------------------------------- runner


def _method_config(specs: Sequence[MethodSpec]) -> dict:
    """Per method name: estimator, constructor and segment arguments (as text)."""
    out = {}
    for spec in specs:
        estimator = getattr(spec.estimator, "__qualname__", repr(spec.estimator))
        params = repr(sorted(spec.params.items()))
        for name, kwargs in spec.variants.items():
            out[name] = {
                "estimator": estimator,
                "params": params,
                "segment": repr(sorted(kwargs.items())),
            }
    return out


def _check_run_config(folder: Path, config: dict) -> None:
    """Refuse to resume a folder written with other settings; methods may be added."""
    path = folder / "run.json"
    previous = None
    if path.is_file():
        try:
            previous = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            previous = None
    if previous is not None:
        changed = [k for k in config if k != "methods" and previous.get(k) != config[k]]
        old_methods = previous.get("methods", {})
        changed += [
            f"method {name!r}"
            for name, value in config["methods"].items()
            if name in old_methods and old_methods[name] != value
        ]
        if changed:
            raise MedsegError(
                f"{folder} holds results of a different run ({', '.join(changed)} "
                "changed); resume with the same settings or choose a new output folder"
            )
        config = config | {"methods": old_methods | config["methods"]}
    with atomic_write(path) as tmp:
        tmp.write_text(json.dumps(config, indent=2, sort_keys=True), encoding="utf-8")


def run_folds(
    cohort,
    specs: Sequence[MethodSpec],
    output_dir: str | os.PathLike,
    *,
    folds: str | int = "loo",
    labels: Sequence[int] = (1,),
    n_landmarks: int | None = None,
    seed: int = 0,
    perturbation: Sequence[float] = (),
    n_jobs: int = 1,
    scheduler: str | None = None,
    save_predictions: bool = True,
    progress: bool = False,
) -> Path:
    """Run (or resume) the cross-validation; one CSV row per (method, case, perturbation).

    Parameters
    ----------
    cohort : Cohort
    specs : sequence of MethodSpec
    output_dir : path
        Gets ``cases.csv`` (see :data:`COLUMNS`) and ``run.json`` (the settings; a resume
        with different settings is refused).
    folds : "loo" or int
    labels : sequence of int
        Labels forming the structure (their union) in the reference label maps.
    n_landmarks : int or None
        Landmarks when they are computed from the label maps (cohorts without landmarks).
    seed : int
    perturbation : sequence of float
        Rotation angles (degrees, in ``(0, 45]``) of the pose-perturbation study; each test
        case is also segmented under a random similarity of each size. Empty: no study.
    n_jobs : int
        Folds run in parallel on this many local processes (joblib); 1 runs serially.
    scheduler : str, optional
        Address of a running Dask scheduler (``"tcp://host:port"``); folds are submitted to
        it (``n_jobs`` is then ignored). The cohort's files must be readable by the workers.
    save_predictions : bool
        Write each unperturbed prediction to ``predictions/<method>/<case>.nii.gz`` (on the
        test image's grid); the report draws its overlays from them. With a Dask cluster,
        ``output_dir`` must then be on a file system the workers share.
    progress : bool
        A progress bar over folds.

    Returns
    -------
    csv_path : pathlib.Path
    """
    labels = tuple(int(v) for v in labels)
    angles = tuple(sorted({0.0} | {float(a) for a in perturbation}))
    if any(not 0.0 <= a <= 45.0 for a in angles):
        raise MedsegError(f"perturbation angles must lie in [0, 45] degrees, got {perturbation}")
    splits = check_cohort(cohort, labels=labels, folds=folds, progress=progress)
    folder = Path(output_dir)
    folder.mkdir(parents=True, exist_ok=True)
    _check_run_config(
        folder,
        {
            "cohort": getattr(cohort, "name", "cohort"),
            "cases": list(cohort.case_ids),
            "folds": folds,
            "labels": list(labels),
            "seed": int(seed),
            "n_landmarks": n_landmarks,
            "methods": _method_config(specs),
        },
    )
    results = _ResultsFile(folder / "cases.csv")
    names = [n for s in specs for n in s.names]
    tasks = []
    for fold, (tr, te) in enumerate(splits):
        test = cohort[te]
        todo = frozenset(
            k
            for name in names
            for case in test
            for a in angles
            if (k := _key(name, fold, case.case_id, a)) not in results.done
        )
        if todo:
            tasks.append(
                FoldTask(
                    fold=fold,
                    train=cohort[tr],
                    test=test,
                    seed=fold_seed(seed, fold),
                    run_seed=int(seed),
                    specs=tuple(specs),
                    labels=labels,
                    n_landmarks=n_landmarks,
                    angles=angles,
                    todo=todo,
                    predictions_dir=str(folder / "predictions") if save_predictions else None,
                )
            )
    bar = tqdm(
        total=len(splits), initial=len(splits) - len(tasks), desc="folds", disable=not progress
    )
    try:
        if scheduler is not None:
            _run_dask(tasks, scheduler, results, bar)
        elif n_jobs == 1 or len(tasks) <= 1:
            for task in tasks:
                run_fold(task, on_row=results.append)
                bar.update()
        else:
            from joblib import Parallel, delayed

            parallel = Parallel(n_jobs=n_jobs, return_as="generator_unordered")
            for rows in parallel(delayed(run_fold)(t) for t in tasks):
                for row in rows:
                    results.append(row)
                bar.update()
    finally:
        bar.close()
    return results.path


def _run_dask(tasks: list[FoldTask], scheduler: str, results: _ResultsFile, bar) -> None:
    try:
        from dask.distributed import Client, as_completed
    except ImportError as exc:  # pragma: no cover - dask[distributed] is a dependency
        raise MedsegError(
            "--scheduler needs dask.distributed: pip install 'dask[distributed]'"
        ) from exc
    try:
        client = Client(scheduler, timeout=DASK_CONNECT_TIMEOUT)
    except OSError as exc:
        raise MedsegError(
            f"cannot reach the Dask scheduler at {scheduler!r} ({exc}); start one with "
            "`dask scheduler` and workers with `dask worker <address>`"
        ) from exc
    with client:
        try:
            client.wait_for_workers(1, timeout=DASK_CONNECT_TIMEOUT)
        except TimeoutError as exc:
            raise MedsegError(
                f"the Dask scheduler at {scheduler!r} has no workers; start some with "
                f"`dask worker {scheduler}`"
            ) from exc
        futures = [client.submit(run_fold, t, pure=False) for t in tasks]
        for future in as_completed(futures):
            for row in future.result():
                results.append(row)
            bar.update()
