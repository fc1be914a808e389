"""The figures that say the method works, on a seeded phantom: floors a regression would break.

One model is trained on 12 phantom subjects and segments 8 held-out ones in their random
poses (no initialisation), once with each part switched off on the same candidates: the
full segmenter, the MRF's landmarks without the active-shape refinement, the detectors
alone (no prior), and the prior without the handedness term. Everything is seeded, so the
figures are reproducible; the floors sit below the values measured on 2026-12-01 (in the
comments) by margins that noise of the implementation cannot take but a broken part does.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from medseg.datasets import make_phantom_cohort
from medseg.evaluation.metrics import dice
from medseg.io import select_labels
from medseg.segmenter import ShapePriorSegmenter

N_TRAIN, N_TEST = 12, 8
VARIANTS = ("full", "mrf", "detection", "no_handedness")


def _error_mm(landmarks: np.ndarray, truth: np.ndarray) -> float:
    return float(np.linalg.norm(landmarks - truth, axis=1).mean())


@pytest.fixture(scope="module")
def figures() -> dict[str, dict[str, np.ndarray]]:
    """Per variant: Dice and mean landmark error (mm) of every held-out case."""
    cohort = make_phantom_cohort(N_TRAIN + N_TEST, random_state=0, n_landmarks=20, size=48)
    model = ShapePriorSegmenter(n_estimators=10, n_candidates=10, random_state=0)
    model.fit(cohort[:N_TRAIN])
    mrf_only = copy.copy(model).set_params(refine_levels=0)
    no_handedness = copy.copy(mrf_only).set_params(orientation_weight=0.0)
    out = {name: {"dice": [], "error": []} for name in VARIANTS}
    for case in cohort[N_TRAIN:]:
        image, truth = case.load_image(), case.load_landmarks()
        reference = select_labels(case.load_label(), (1,))
        full = model.segment(image)
        cands = full.candidates
        results = {
            "full": full,
            "mrf": mrf_only.segment(image, candidates=cands),
            "detection": model.segment(image, use_prior=False, candidates=cands),
            "no_handedness": no_handedness.segment(image, candidates=cands),
        }
        for name, seg in results.items():
            out[name]["dice"].append(dice(seg.label, reference))
            out[name]["error"].append(_error_mm(seg.landmarks, truth))
    return {name: {k: np.asarray(v) for k, v in d.items()} for name, d in out.items()}


@pytest.mark.slow
def test_full_segmenter_reaches_its_figures(figures):
    full = figures["full"]
    # measured: Dice mean 0.739, median 0.888; landmark error median 1.89 mm (5 of 8 cases
    # under 2 mm, 3 on a wrong configuration at 13-16 mm)
    assert full["dice"].mean() >= 0.65
    assert np.median(full["dice"]) >= 0.80
    assert np.median(full["error"]) <= 3.0


@pytest.mark.slow
def test_shape_prior_beats_detection_alone(figures):
    mrf, detection = figures["mrf"], figures["detection"]
    # measured (the MRF's landmarks, no refinement): Dice 0.557 with the prior, 0.240 with
    # each landmark at its best candidate; better in 8 of 8 cases; median error 5.2 / 10.9 mm
    assert mrf["dice"].mean() >= detection["dice"].mean() + 0.2
    assert (mrf["dice"] > detection["dice"]).sum() >= 7
    assert np.median(mrf["error"]) <= np.median(detection["error"]) - 3.0


@pytest.mark.slow
def test_handedness_term_helps(figures):
    mrf, plain = figures["mrf"], figures["no_handedness"]
    # measured: Dice 0.557 with the handedness term, 0.484 without; median error 5.2 / 7.4 mm
    assert mrf["dice"].mean() >= plain["dice"].mean() + 0.03
    assert np.median(mrf["error"]) <= np.median(plain["error"]) - 1.0


@pytest.mark.slow
def test_refinement_improves_the_mrf_landmarks(figures):
    full, mrf = figures["full"], figures["mrf"]
    # measured: median landmark error 1.89 mm refined, 5.17 mm the MRF's choice
    assert np.median(full["error"]) <= np.median(mrf["error"]) - 2.0
