"""medseg evaluation stage: subject-grouped cross-validation with baselines, reports.

* :func:`run_evaluation` (what ``medseg-evaluate`` calls): cohort -> folds -> report folder;
* :mod:`evaluation.crossval`: folds, the resumable per-case runner (joblib / Dask);
* :mod:`evaluation.baselines`: the active shape model;
* :mod:`evaluation.perturbation`: pose perturbation of test cases;
* :mod:`evaluation.report`: summary table, summary.json, figures;
* :mod:`evaluation.metrics`: Dice, HD95, ASSD, landmark error.

The names below are imported lazily, so ``import evaluation.metrics`` stays light.
"""

from __future__ import annotations

__all__ = ["run_evaluation", "resolve_cohort", "DEFAULT_PERTURBATION"]


def __getattr__(name: str):
    if name in __all__:
        from evaluation import evaluate

        return getattr(evaluate, name)
    raise AttributeError(f"module 'evaluation' has no attribute {name!r}")
