"""How well a segmenter's own quality score flags its failures.

``Segmentation.quality["score"]`` (kept in the ``quality`` column of ``cases.csv``) is meant
to be high where the segmentation is wrong. Scored against the truth of a cross-validation:
the ROC AUC of the score for telling cases with a Dice under a threshold (failures) from
the others, and how many failures the segmenter's own flag (score above
``QUALITY_THRESHOLD``) catches, and at what cost in false alarms.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["FAILURE_DICE", "flagging_scores"]

#: Dice under which a case counts as failed (issue 17's definition).
FAILURE_DICE = 0.75


def flagging_scores(
    rows: Sequence[dict], *, failure_dice: float = FAILURE_DICE, threshold: float | None = None
) -> dict:
    """Per method with a quality score: ROC AUC and flag counts.

    Parameters
    ----------
    rows : sequence of dict
        Rows of :func:`medseg.evaluation.results.read_results` (one condition, usually the
        unperturbed one); rows without a finite ``quality`` are left out.
    failure_dice : float
        A case whose Dice is under this failed.
    threshold : float, optional
        Score above which the segmenter flags a case; default
        :data:`medseg.segmenter.QUALITY_THRESHOLD`.

    Returns
    -------
    scores : dict
        ``{method: {"n", "failed", "auc", "flagged", "flagged_failed"}}``; ``auc`` is NaN
        when every case, or none, failed.
    """
    from sklearn.metrics import roc_auc_score

    if threshold is None:
        from medseg.segmenter import QUALITY_THRESHOLD as threshold
    by_method: dict[str, list[tuple[float, float]]] = {}
    for r in rows:
        if np.isfinite(r.get("quality", math.nan)):
            by_method.setdefault(r["method"], []).append((r["quality"], r["dice"]))
    out = {}
    for method, pairs in by_method.items():
        quality, dice = np.asarray(pairs, dtype=float).T
        failed = dice < failure_dice
        flagged = quality > threshold
        both = failed.any() and not failed.all()
        out[method] = {
            "n": int(len(dice)),
            "failed": int(failed.sum()),
            "auc": float(roc_auc_score(failed, quality)) if both else math.nan,
            "flagged": int(flagged.sum()),
            "flagged_failed": int((flagged & failed).sum()),
        }
    return out
