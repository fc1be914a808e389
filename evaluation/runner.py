"""The cross-validation runner: every fold, serially, on local cores or on a Dask cluster.

:func:`run_folds` checks the cohort (:func:`medseg.evaluation.folds.check_cohort`), records
the run's settings in ``run.json`` (a resume with other settings is refused), and hands one
:class:`~medseg.evaluation.fold.FoldTask` per fold with work left to
:func:`~medseg.evaluation.fold.run_fold`. Each row is appended to ``cases.csv``
(:class:`~medseg.evaluation.results.ResultsFile`) as it arrives, so a rerun on the same
folder skips the rows already there. Folds run serially, on local cores (joblib,
``n_jobs``), or on an existing Dask cluster (``scheduler="tcp://host:port"``); every fold's
seed derives from ``seed`` and the fold number only
(:func:`~medseg.evaluation.folds.fold_seed`), so the numbers do not depend on where or in
which order folds run.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path

from tqdm.auto import tqdm

from medseg.errors import MedsegError
from medseg.evaluation.fold import FoldTask, run_fold
from medseg.evaluation.folds import check_cohort, fold_seed
from medseg.evaluation.methods import MethodSpec
from medseg.evaluation.perturbation import LABEL_INTERPOLATION, check_conditions
from medseg.evaluation.results import ResultsFile, read_results, result_key
from medseg.io import atomic_write

__all__ = ["run_folds", "DASK_CONNECT_TIMEOUT"]

#: How long to wait for a Dask scheduler before giving up.
DASK_CONNECT_TIMEOUT = "20s"


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
        for name, (variant, attribute) in spec.derived.items():
            out[name] = {**out[variant], "label": attribute}
        for name, (variant, function) in spec.oracles.items():
            target = getattr(function, "func", function)
            keywords = sorted(getattr(function, "keywords", {}).items())
            oracle = f"{getattr(target, '__qualname__', repr(target))}{keywords!r}"
            out[name] = {**out[variant], "oracle": oracle}
    return out


def _check_run_config(folder: Path, config: dict) -> None:
    """Refuse to resume a folder written with other settings; methods may be added, and a
    method without rows yet (an extension stopped before any of its folds ended) may be
    given other settings."""
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
        scored = {row["method"] for row in read_results(folder / "cases.csv")}
        changed += [
            f"method {name!r}"
            for name, value in config["methods"].items()
            if name in old_methods and old_methods[name] != value and name in scored
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
    perturbation: Sequence[str] = (),
    n_jobs: int = 1,
    scheduler: str | None = None,
    save_predictions: bool = True,
    keep_models: bool = False,
    progress: bool = False,
) -> Path:
    """Run (or resume) the cross-validation; one CSV row per (method, case, condition).

    Parameters
    ----------
    cohort : Cohort
    specs : sequence of MethodSpec
    output_dir : path
        Gets ``cases.csv`` (see :data:`medseg.evaluation.results.COLUMNS`) and ``run.json``
        (the settings; a resume with different settings is refused).
    folds : "loo" or int
    labels : sequence of int
        Labels forming the structure (their union) in the reference label maps.
    n_landmarks : int or None
        Landmarks when they are computed from the label maps (cohorts without landmarks).
    seed : int
    perturbation : sequence of str
        Named conditions of the pose-perturbation study
        (:func:`medseg.evaluation.perturbation.parse_condition`: ``random``, ``rot90``,
        ``scale0.8``, ``pad_zeros``, ...); each test case is also segmented under each, its
        copy seeded by ``seed``, the case and the condition. The unperturbed case
        (``acquired``) is always run. Empty: no study. Conditions may be added when
        resuming; the rows already there are kept.
    n_jobs : int
        Folds run in parallel on this many local processes (joblib); 1 runs serially.
    scheduler : str, optional
        Address of a running Dask scheduler (``"tcp://host:port"``); folds are submitted to
        it (``n_jobs`` is then ignored). The cohort's files must be readable by the workers.
    keep_models : bool
        Keep each fold's fitted segmenter in ``models/`` and reuse it when the run is
        resumed or extended (:func:`medseg.evaluation.fold._fitted`): the same training
        cases, parameters, seed and source code, or it is fitted again.
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
    conditions = check_conditions(perturbation)  # ParameterError before any work
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
            # rows scored against references resampled otherwise are not comparable
            "reference_labels": LABEL_INTERPOLATION,
            "methods": _method_config(specs),
        },
    )
    results = ResultsFile(folder / "cases.csv")
    names = [n for s in specs for n in s.names]
    tasks = []
    for fold, (tr, te) in enumerate(splits):
        test = cohort[te]
        todo = frozenset(
            k
            for name in names
            for case in test
            for condition in conditions
            if (k := result_key(name, fold, case.case_id, condition)) not in results.done
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
                    conditions=conditions,
                    todo=todo,
                    predictions_dir=str(folder / "predictions") if save_predictions else None,
                    models_dir=str(folder / "models") if keep_models else None,
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


def _run_dask(tasks: list[FoldTask], scheduler: str, results: ResultsFile, bar) -> None:
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
