"""The figures that say the method works, on a seeded phantom: floors a regression would break.

One model is trained on 12 phantom subjects and segments 8 held-out ones in their random
poses (no initialisation), once with each part switched off on the same candidates: the
full segmenter, the MRF's landmarks without the active-shape refinement, and the detectors
alone (no prior). Everything is seeded, so the figures are reproducible. On 8 cases the
outcomes are bimodal and which cases land on a wrong configuration changes with any change
of the random draws, so the floors are set on what the model's figures share over seeds:
measured with seeds 0-4 of this code and 0-2 of the code before it (2026-12-01/03), the
ranges in the comments. A broken part falls far below them (detection alone: Dice 0.24).

The handedness term is not among the parts: over those seeds it changed the MRF's mean
Dice by -0.08 to +0.14 (mean +0.01), no effect that 8 cases can show;
``tests/test_orientation.py`` tests what it does (a mirror labelling costs more).
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
VARIANTS = ("full", "mrf", "detection")
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

    The floors of the parts (prior, refinement) were measured with it; posed
    copies change the candidates the parts work on (``posed_model``). Without the
    appearance check, which may replace what the parts found (``tests/test_appearance.py``;
    ``posed_model`` has it).
    """
    return ShapePriorSegmenter(
        n_estimators=10,
        n_candidates=10,
        augment_poses=0,
        appearance_check=False,
        random_state=0,
        n_jobs=2,
    ).fit(cohort[:N_TRAIN])


@pytest.fixture(scope="module")
def posed_model(cohort) -> ShapePriorSegmenter:
    """The shipped defaults: detectors also trained on posed copies of every subject."""
    return ShapePriorSegmenter(n_estimators=10, n_candidates=10, random_state=0, n_jobs=2).fit(
        cohort[:N_TRAIN]
    )


@pytest.fixture(scope="module")
def figures(cohort, model) -> dict[str, dict[str, np.ndarray]]:
    """Per variant: Dice and mean landmark error (mm) of every held-out case."""
    mrf_only = copy.copy(model).set_params(refine_levels=0)
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
        }
        for name, seg in results.items():
            out[name]["dice"].append(dice(seg.label, reference))
            out[name]["error"].append(_error_mm(seg.landmarks, truth))
    return {name: {k: np.asarray(v) for k, v in d.items()} for name, d in out.items()}


#: A case whose landmarks are on the right configuration (mm, mean over landmarks): the
#: phantom's outcomes are bimodal, about 1-4 mm or 10-23 mm (with or without refinement).
RIGHT_MM = 5.0


@pytest.mark.slow
def test_full_segmenter_reaches_its_figures(figures):
    full = figures["full"]
    right = full["error"] < RIGHT_MM
    # measured with this fixture's seed (2026-12-03): Dice mean 0.66, median 0.86; 3 of 8
    # cases right, at 0.9-1.9 mm. Over seeds 0-4 of the model (and 1-2 before the training
    # copies ran in parallel): mean 0.64-0.75, median 0.80-0.93, 1.3-2.4 mm (median) on the
    # 3-5 cases that are right. Which cases land on a wrong configuration changes with the
    # seed, so the floors are on what all seeds share.
    assert full["dice"].mean() >= 0.60
    assert np.median(full["dice"]) >= 0.75
    assert right.sum() >= 2
    assert np.median(full["error"][right]) <= 3.0


@pytest.mark.slow
def test_shape_prior_beats_detection_alone(figures):
    mrf, detection = figures["mrf"], figures["detection"]
    gain = mrf["dice"] - detection["dice"]
    # measured (the MRF's landmarks, no refinement, against each landmark at its best
    # candidate): Dice gain 0.46 on average, 0.46 per case (median); mean landmark error
    # 8.1 / 12.1 mm. Over seeds: mean gain 0.32-0.53, median 0.31-0.61, error lower by
    # 1.6-5.7 mm; detection alone never reaches a Dice of 0.37
    assert gain.mean() >= 0.2
    assert np.median(gain) >= 0.2
    assert mrf["error"].mean() <= detection["error"].mean() - 0.5
    assert detection["dice"].max() < 0.5


@pytest.mark.slow
def test_refinement_improves_the_mrf_landmarks(figures):
    """Where the MRF chose the right configuration, the active-shape search moves its
    landmarks closer to the truth (it is a local search: from a wrong configuration it
    stays wrong, or, rarely, finds the right one)."""
    full, mrf = figures["full"], figures["mrf"]
    right = mrf["error"] < RIGHT_MM
    gain = (mrf["error"] - full["error"])[right]
    # measured: 3 cases right, each closer after the search (median 1.9 mm closer). Over
    # seeds: 1-4 cases right, 2 of 3 to all closer, by 1.6-2.4 mm (median)
    assert right.sum() >= 1
    assert np.median(gain) >= 0.5
    assert (gain > 0).mean() >= 0.6


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
    case by case where both runs are right; on average it asks only for what detectors
    trained on the crops alone break (rotated Dice 0.19-0.26, padding alone 0.20). The
    means of 8 cases cannot show more: over seeds 0-3 of the model the rotated mean Dice
    was 0.15 above to 0.39 below the acquired one (cases right rotated / acquired: 5 / 4,
    5 / 4, 2 / 7, 7 / 6).
    """
    # measured with this fixture's seed (2026-12-03): Dice mean 0.59 acquired, 0.73
    # rotated; where both are right (2 cases) the landmarks disagree by 0.8 and 1.1 mm and
    # the Dice by 0.02. Over seeds 0-3: rotated mean 0.47-0.84; 2-5 cases right in both
    # runs, disagreeing by 0.9-2.4 mm (median) and 0.012-0.040 Dice (mean)
    right, posed_right = posed["error"] < RIGHT_MM, posed["posed_error"] < RIGHT_MM
    both = right & posed_right
    assert posed["posed_dice"].mean() >= 0.40
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
