"""Folds by subject, their seeds, and the checks a cohort must pass before any work.

* :func:`make_folds`: leave-one-subject-out (``"loo"``) or k-fold grouped by subject
  (scikit-learn's ``LeaveOneGroupOut`` / ``GroupKFold`` on ``cohort.subjects``): the cases
  of one person are never split between training and test;
* :func:`fold_seed`: the seed of one fold, a function of the run's seed and the fold number
  only, so the numbers do not depend on where or in which order folds run;
* :func:`check_cohort`: the checks that run before any work (empty cohort, one subject,
  labels no case contains, folds too small to train on); returns the folds.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from sklearn.model_selection import GroupKFold, LeaveOneGroupOut
from tqdm.auto import tqdm

from medseg.errors import CohortError, LabelError, MedsegError
from medseg.segmenter import MIN_TRAINING_CASES

__all__ = ["make_folds", "fold_seed", "check_cohort"]


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
        is smaller than :data:`medseg.segmenter.MIN_TRAINING_CASES`, or a case without a
        label map.
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
