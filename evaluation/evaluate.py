"""One call for the whole evaluation: cohort -> cross-validation -> report folder.

:func:`run_evaluation` is what ``medseg-evaluate`` calls: it resolves the cohort (an MSD /
nnU-Net folder, a CSV manifest, ``"phantom"`` or an in-memory :class:`Cohort`), checks it
before any work, runs (or resumes) the subject-grouped cross-validation of the method and
its baselines with the pose-perturbation study, and writes the report.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from medseg.errors import CohortError
from medseg.evaluation.folds import check_cohort
from medseg.evaluation.methods import (
    DEFAULT_METHODS,
    DEFAULT_PERTURBATION,
    MethodSpec,
    default_methods,
    resolve_methods,
)
from medseg.evaluation.perturbation import check_conditions
from medseg.evaluation.report import write_report
from medseg.evaluation.runner import run_folds

__all__ = ["run_evaluation", "resolve_cohort", "DEFAULT_PERTURBATION"]


def resolve_cohort(source, *, seed: int = 0, max_subjects: int | None = None):
    """A :class:`~medseg.datasets.Cohort` from a path, ``"phantom"`` or a cohort.

    Parameters
    ----------
    source : Cohort, path or "phantom"
        ``"phantom"`` is the embedded default: 20 synthetic subjects with random poses
        (``make_phantom_cohort(20, random_state=seed)``).
    seed : int
    max_subjects : int, optional
        Keep the cases of the first ``max_subjects`` subjects (in order of appearance):
        a subject-grouped subset, e.g. for leave-one-out on part of a large cohort.
    """
    from medseg.datasets import Cohort, load_cohort, make_phantom_cohort

    if isinstance(source, str) and source == "phantom":
        cohort = make_phantom_cohort(20, random_state=seed)
    elif isinstance(source, Cohort):
        cohort = source
    elif isinstance(source, str | os.PathLike):
        cohort = load_cohort(source)
    else:
        raise TypeError(f"`cohort` must be a Cohort, a path or 'phantom', got {type(source)}")
    if max_subjects is not None:
        if max_subjects < 2:
            raise CohortError(f"`max_subjects` must be at least 2, got {max_subjects}")
        subjects = list(dict.fromkeys(np.asarray(cohort.subjects).tolist()))[:max_subjects]
        cohort = cohort[np.flatnonzero(np.isin(cohort.subjects, subjects))]
    return cohort


def run_evaluation(
    cohort,
    output_dir: str | os.PathLike,
    *,
    folds: str | int = "loo",
    methods: Iterable[str | MethodSpec] = DEFAULT_METHODS,
    labels: Sequence[int] = (1,),
    n_landmarks: int | None = None,
    seed: int = 0,
    n_jobs: int = 1,
    scheduler: str | None = None,
    perturbation: Sequence[str] = DEFAULT_PERTURBATION,
    max_subjects: int | None = None,
    segmenter_params: dict | None = None,
    asm_params: dict | None = None,
    multi_atlas_params: dict | None = None,
    report: bool = True,
    keep_models: bool = False,
    progress: bool = False,
) -> Path:
    """Cross-validate the method and its baselines by subject and write the report.

    Parameters
    ----------
    cohort : Cohort, path or "phantom"
        MSD / nnU-Net folder, CSV manifest, in-memory cohort, or the synthetic phantom.
    output_dir : path
        Report folder: ``cases.csv``, ``run.json``, ``predictions/``, ``summary.md``,
        ``summary.json`` and the figures (see :func:`medseg.evaluation.report.write_report`).
        Rerunning on the same folder resumes: finished (fold, method, case, condition) rows
        are kept and not recomputed.
    folds : "loo" or int, default "loo"
        Leave-one-subject-out, or k-fold grouped by subject.
    methods : iterable of str or MethodSpec, default :data:`DEFAULT_METHODS`
        The method, its label map before the regional stage (``shape_only``), its
        detection-only baseline (same fitted model, ``use_prior=False``) and the active
        shape model (``asm_boundary`` adds it with the regional stage); ``"multi_atlas"``
        adds the multi-atlas registration baseline
        (:mod:`medseg.evaluation.baselines.multi_atlas`; not in the default, it registers
        9 atlases per test input); ``"ceiling"`` and ``"ceiling_boundary"`` the template
        on each case's reference landmarks, without and with the stage (a yardstick,
        :mod:`medseg.evaluation.ceiling`); :class:`MethodSpec` objects add other estimators.
    labels : sequence of int, default (1,)
        Labels forming the structure (their union), e.g. ``(1, 2)`` for the hippocampus.
    n_landmarks : int, optional
        Landmarks per shape when they are computed from the label maps.
    seed : int, default 0
        Seeds the phantom, every fold and the perturbations: the same seed gives the same
        numbers, serially or in parallel.
    n_jobs : int, default 1
        Folds in parallel on local processes (joblib).
    scheduler : str, optional
        ``"tcp://host:port"`` of a running Dask scheduler: folds run on its workers.
    perturbation : sequence of str, default ("rot90", "scale1.25", "random")
        Named conditions of the pose-perturbation study
        (:mod:`medseg.evaluation.perturbation`: ``rotN``, ``scaleS``, ``pad_zeros``,
        ``pad_noise``, ``random``); empty to skip it.
    max_subjects : int, optional
        Evaluate only the cases of the first ``max_subjects`` subjects.
    segmenter_params, asm_params, multi_atlas_params : dict, optional
        Extra constructor arguments of the segmenter / the ASM / the multi-atlas baseline.
    report : bool, default True
        Write the report after the runs.
    keep_models : bool, default False
        Keep each fold's fitted segmenter in ``models/`` of the report folder (about 10 MB
        each on the hippocampus) and, when the run is resumed or extended with more
        conditions or methods, load it instead of fitting again (only if it was fitted on
        the same cases, with the same parameters, seed and source code).
    progress : bool, default False
        Progress bars (folds).

    Returns
    -------
    output_dir : pathlib.Path

    Raises
    ------
    ParameterError
        Before any work: an unknown perturbation condition.
    CohortError, LabelError
        Before any work: an empty cohort, a single subject, a label no case contains,
        folds too small to train on, a resume with different settings.
    """
    check_conditions(perturbation)  # a typo in a name is refused before the cohort is read
    labels = tuple(int(v) for v in labels)
    cohort = resolve_cohort(cohort, seed=seed, max_subjects=max_subjects)
    check_cohort(cohort, labels=labels, folds=folds, progress=progress)
    methods = list(methods)
    names = [m for m in methods if isinstance(m, str)]
    specs = [m for m in methods if isinstance(m, MethodSpec)]
    if names:
        specs = (
            list(
                default_methods(
                    names,
                    labels=labels,
                    n_landmarks=n_landmarks,
                    segmenter_params=segmenter_params,
                    asm_params=asm_params,
                    multi_atlas_params=multi_atlas_params,
                )
            )
            + specs
        )
    specs = resolve_methods(specs, labels=labels, n_landmarks=n_landmarks)
    folder = Path(output_dir)
    run_folds(
        cohort,
        specs,
        folder,
        folds=folds,
        labels=labels,
        n_landmarks=n_landmarks,
        seed=seed,
        perturbation=perturbation,
        n_jobs=n_jobs,
        scheduler=scheduler,
        keep_models=keep_models,
        progress=progress,
    )
    if report:
        write_report(folder, cohort, labels=labels, title=f"medseg evaluation: {cohort.name}")
    return folder
