"""medseg evaluation stage: subject-grouped cross-validation with baselines, reports.

* :func:`run_evaluation` (what ``medseg-evaluate`` calls): cohort -> folds -> report folder;
* :mod:`medseg.evaluation.folds`: folds by subject, their seeds, the cohort checks;
* :mod:`medseg.evaluation.fold`: one fold's work (fit, segment, score, save predictions);
* :mod:`medseg.evaluation.runner`: the resumable runner over folds (serial, joblib, Dask);
* :mod:`medseg.evaluation.results`: the per-case CSV (columns, reading, resuming);
* :mod:`medseg.evaluation.methods`: the method and baselines compared, built per fold;
* :mod:`medseg.evaluation.references`: reference landmarks of each fold's cases;
* :mod:`medseg.evaluation.baselines`: the active shape model, multi-atlas registration;
* :mod:`medseg.evaluation.perturbation`: pose perturbation of test cases, the named
  conditions of the study (shared with ``benchmarks/bench_pose_study.py``);
* :mod:`medseg.evaluation.report`: summary table, summary.json, figures;
* :mod:`medseg.evaluation.metrics`: Dice, HD95, ASSD, landmark error.

The names below are imported lazily, so ``import medseg.evaluation.metrics`` stays light.
"""

from __future__ import annotations

__all__ = ["run_evaluation", "resolve_cohort", "DEFAULT_PERTURBATION"]


def __getattr__(name: str):
    if name in __all__:
        from medseg.evaluation import evaluate

        return getattr(evaluate, name)
    raise AttributeError(f"module 'medseg.evaluation' has no attribute {name!r}")
