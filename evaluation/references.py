"""Reference landmarks for cohorts that have none (real data: label maps only).

The phantom carries ground-truth landmarks per case; a real cohort such as the MSD
hippocampus does not. There, per fold:

* the training landmarks come from :func:`medseg.correspondence.landmarks_from_labels` on the
  training label maps, computed **once** and attached to the training cases, so every method
  of the fold (the segmenter, the detection baseline and the ASM) trains on the same
  landmarks;
* a test case's reference landmarks are the template's landmarks carried onto its label map
  by :func:`medseg.correspondence.transfer_landmarks`, the same transfer the training
  cases got.

The landmark error on real data is therefore measured against a registration-derived
reference, not against expert landmarks: it is a consistency measure and is reported as such.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from medseg.correspondence import landmarks_from_labels, transfer_landmarks

__all__ = ["fold_landmarks"]


def fold_landmarks(train, test, *, labels, n_landmarks: int | None, seed: int):
    """Training cohort with landmarks, and reference landmarks of the test cases.

    Parameters
    ----------
    train, test : Cohort
    labels : tuple of int
    n_landmarks : int or None
    seed : int

    Returns
    -------
    train : Cohort
        ``train`` itself when every case carries landmarks, else a copy whose cases carry
        the landmarks computed from their label maps (cases whose correspondence failed are
        left out).
    references : list of (N, 3) float array or None
        Per test case: its own landmarks, or the template's transferred onto its label map.
    """
    given = [case.load_landmarks() for case in train]
    if all(lm is not None for lm in given):
        return train, [case.load_landmarks() for case in test]
    corr = landmarks_from_labels(
        [case.load_label() for case in train],
        n_landmarks=n_landmarks,
        labels=tuple(labels),
        random_state=seed,
        keep_largest=True,
        case_ids=[case.case_id for case in train],
    )
    keep = ~np.asarray(corr.failed, dtype=bool)
    landmarks = np.asarray(corr.landmarks, dtype=float)
    cases = [
        dataclasses.replace(case, landmarks=landmarks[i]) for i, case in enumerate(train) if keep[i]
    ]
    template_landmarks = landmarks[int(corr.reference_index)]
    references = []
    for case in test:
        own = case.load_landmarks()
        if own is not None and own.shape == template_landmarks.shape:
            references.append(own)
        else:
            references.append(
                transfer_landmarks(
                    corr.reference_surface,
                    template_landmarks,
                    case.load_label(),
                    labels=labels,
                    keep_largest=True,
                    random_state=seed,
                )
            )
    return dataclasses.replace(train, cases=cases), references
