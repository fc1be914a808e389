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
import SimpleITK as sitk

from medseg.datasets import make_phantom_cohort
from medseg.evaluation.metrics import dice
from medseg.evaluation.perturbation import perturb_condition
from medseg.io import select_labels
from medseg.segmenter import ShapePriorSegmenter

N_TRAIN, N_TEST = 12, 8
VARIANTS = ("full", "mrf", "detection", "no_handedness")
#: Rotation of the end-to-end pose test (degrees): the issue's range ends at 45.
POSE_ANGLE_DEG = 45


def _error_mm(landmarks: np.ndarray, truth: np.ndarray) -> float:
    return float(np.linalg.norm(landmarks - truth, axis=1).mean())


@pytest.fixture(scope="module")
def cohort():
    return make_phantom_cohort(N_TRAIN + N_TEST, random_state=0, n_landmarks=20, size=48)


@pytest.fixture(scope="module")
def model(cohort) -> ShapePriorSegmenter:
    """The parts' model: detectors trained on the subjects as they are (no posed copies).

    The floors of the parts (prior, handedness, refinement) were measured with it; posed
    copies change the candidates the parts work on (``posed_model``).
    """
    return ShapePriorSegmenter(
        n_estimators=10, n_candidates=10, augment_poses=0, random_state=0
    ).fit(cohort[:N_TRAIN])


@pytest.fixture(scope="module")
def posed_model(cohort) -> ShapePriorSegmenter:
    """The shipped defaults: detectors also trained on posed copies of every subject."""
    return ShapePriorSegmenter(n_estimators=10, n_candidates=10, random_state=0).fit(
        cohort[:N_TRAIN]
    )


@pytest.fixture(scope="module")
def figures(cohort, model) -> dict[str, dict[str, np.ndarray]]:
    """Per variant: Dice and mean landmark error (mm) of every held-out case."""
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


@pytest.fixture(scope="module")
def posed(cohort, posed_model) -> dict[str, np.ndarray]:
    """Each held-out case segmented as it is and under a resampled similarity.

    The similarity: a rotation by ``POSE_ANGLE_DEG`` about a random axis through the image
    centre, on a grid padded by 15 mm (``perturb_condition``, seeded by the case). Per case:
    the Dice and landmark error of both runs, and their disagreement (mm, mean over
    landmarks): the posed run's landmarks against the acquired run's mapped by the transform.
    """
    out = {"dice": [], "posed_dice": [], "error": [], "posed_error": [], "disagreement": []}
    for k, case in enumerate(cohort[N_TRAIN:]):
        image, truth = case.load_image(), case.load_landmarks()
        reference = select_labels(case.load_label(), (1,))
        moved, moved_label, moved_truth, change, centre = perturb_condition(
            f"rot{POSE_ANGLE_DEG}", image, reference, truth, random_state=k
        )
        acquired, again = posed_model.segment(image), posed_model.segment(moved)
        out["dice"].append(dice(acquired.label, reference))
        out["posed_dice"].append(dice(again.label, moved_label))
        out["error"].append(_error_mm(acquired.landmarks, truth))
        out["posed_error"].append(_error_mm(again.landmarks, moved_truth))
        mapped = change.apply(acquired.landmarks, centre)
        out["disagreement"].append(_error_mm(again.landmarks, mapped))
    return {k: np.asarray(v) for k, v in out.items()}


@pytest.mark.slow
def test_segmentation_does_not_depend_on_the_pose(posed):
    """End to end: the same phantom case as acquired and rotated by 45 degrees, padded.

    The phantom's outcomes are bimodal: a run finds the right configuration (about 2 mm) or
    a wrong one (12-20 mm; see the full segmenter's figures), and which cases land on a wrong
    one changes with any change of the input, pose or not. So the test asks for invariance
    case by case where both runs are right, and on average otherwise; the floor on the
    rotated Dice is what detectors trained on the crops alone break (0.19-0.26, padding
    alone 0.20).
    """
    # measured on 2026-12-01 (detectors with posed copies at scales 0.7-1.4): Dice mean
    # 0.793 acquired, 0.759 rotated (0.733 / 0.777 with scales 0.8-1.25); right (< 5 mm) in
    # 6 and 4 of 8 cases; where both are right (2 cases) the landmarks disagree by 1.9 and
    # 4.0 mm (two runs of about 2 mm error each) and the Dice by 0.025 on average
    right, posed_right = posed["error"] < 5.0, posed["posed_error"] < 5.0
    both = right & posed_right
    assert posed["posed_dice"].mean() >= 0.65
    assert posed["posed_dice"].mean() >= posed["dice"].mean() - 0.08
    assert both.sum() >= 1
    assert np.median(posed["disagreement"][both]) <= 4.5
    assert np.abs(posed["posed_dice"] - posed["dice"])[both].mean() <= 0.05


@pytest.mark.slow
def test_the_ceiling_is_the_segmenter_on_other_landmarks(cohort, model):
    """``medseg-evaluate``'s ceiling methods: the same warp and stage as the segmenter, fed
    the reference landmarks instead of the found ones."""
    from medseg.evaluation.ceiling import reference_ceiling

    def array(label):
        return sitk.GetArrayFromImage(label)

    gains = []
    for case in cohort[N_TRAIN : N_TRAIN + 3]:
        image, truth = case.load_image(), select_labels(case.load_label(), (1,))
        seg = model.segment(image)
        own = reference_ceiling(model, image, seg.landmarks, boundary=False)
        own_refined = reference_ceiling(model, image, seg.landmarks, boundary=True)
        np.testing.assert_array_equal(array(own.label), array(seg.shape_label))
        np.testing.assert_array_equal(array(own_refined.label), array(seg.label))
        ceiling = reference_ceiling(model, image, case.load_landmarks(), boundary=False)
        gains.append(dice(ceiling.label, truth) - dice(seg.shape_label, truth))
    assert min(gains) > 0.0  # the true landmarks carry the template closer to the truth
    assert reference_ceiling(model, image, None, boundary=False) is None
    assert reference_ceiling(model, image, seg.landmarks[:-1], boundary=True) is None
