"""The shape's own frame: pose free, training-like, and safe to store."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from medseg.datasets import make_phantom_cohort
from medseg.errors import ModelFileError, ParameterError
from medseg.evaluation.metrics import dice
from medseg.evaluation.perturbation import perturb_case, pose_change
from medseg.frame import ShapeFrame
from medseg.io import save_arrays


@pytest.fixture(scope="module")
def cohort():
    return make_phantom_cohort(6, random_state=3, n_landmarks=20, size=48)


@pytest.fixture(scope="module")
def frame(cohort):
    shapes = np.stack([case.load_landmarks() for case in cohort[:5]])
    return ShapeFrame.fit(shapes, [case.load_image() for case in cohort[:5]])


def test_frame_box_is_a_training_field_of_view(frame, cohort):
    # the phantom's images are 48 voxels of 1 mm; its subjects are scaled by 0.8-1.25, so in
    # the frame (mean size) a field of view is 48 mm / scale across
    extent = frame.upper - frame.lower
    assert np.all(extent > 30) and np.all(extent < 65)
    assert frame.spacing == pytest.approx(1.0)
    inside = (frame.reference > frame.lower) & (frame.reference < frame.upper)
    assert inside.all()


def test_a_case_and_its_similarity_copy_look_the_same_in_the_frame(frame, cohort):
    case = cohort[5]
    image, label, landmarks = case.load_image(), case.load_label(), case.load_landmarks()
    change = pose_change(angle_deg=70.0, scale=1.2, random_state=1)
    moved, moved_label, moved_landmarks = perturb_case(
        image, label, landmarks, change, pad_mm=10.0, fill="zeros"
    )
    a = frame.resample(image, frame.pose(landmarks))
    b = frame.resample(moved, frame.pose(moved_landmarks))
    assert a.GetSize() == b.GetSize() and a.GetOrigin() == b.GetOrigin()
    va, vb = sitk.GetArrayFromImage(a), sitk.GetArrayFromImage(b)
    # Around the structure (within 16 mm of its centre, inside both fields of view) the same
    # voxels up to two linear interpolations: measured correlation 0.996 (0.62 over the
    # whole box, whose corners the rotated copy's field of view does not reach).
    zyx = np.argwhere(np.ones(va.shape, dtype=bool))
    centre = np.asarray(a.TransformPhysicalPointToContinuousIndex(
        frame.reference.mean(axis=0).tolist()))[::-1]  # fmt: skip
    near = np.linalg.norm((zyx - centre) * frame.spacing, axis=1) < 16.0
    sel = tuple(zyx[near].T)
    assert np.corrcoef(va[sel], vb[sel])[0, 1] > 0.98
    la = frame.resample(label, frame.pose(landmarks), is_label=True)
    lb = frame.resample(moved_label, frame.pose(moved_landmarks), is_label=True)
    assert dice(la, lb) > 0.9
    # and the landmarks sit where the reference says
    np.testing.assert_allclose(
        frame.pose(moved_landmarks)(moved_landmarks), frame.pose(landmarks)(landmarks), atol=1e-6
    )


def test_resampling_puts_the_structure_at_the_reference(frame, cohort):
    case = cohort[5]
    label, landmarks = case.load_label(), case.load_landmarks()
    canonical = frame.resample(label, frame.pose(landmarks), is_label=True)
    fg = np.argwhere(sitk.GetArrayViewFromImage(canonical) > 0)[:, ::-1]  # (x, y, z) index
    centroid = np.asarray([canonical.TransformContinuousIndexToPhysicalPoint(p.tolist())
                           for p in fg.astype(float)]).mean(axis=0)  # fmt: skip
    assert np.linalg.norm(centroid - frame.reference.mean(axis=0)) < 2.0


def test_turn_is_the_rotation_between_two_configurations_whatever_their_size(frame, cohort):
    landmarks = cohort[5].load_landmarks()
    centre = landmarks.mean(axis=0)
    assert frame.turn_deg(landmarks, landmarks) == pytest.approx(0.0, abs=1e-4)
    for angle in (10.0, 35.0, 120.0, 179.0):
        turn = Rotation.from_rotvec(np.deg2rad(angle) * np.array([0.6, -0.0, 0.8]))
        # turned about any point, scaled and shifted: only the rotation counts
        other = 1.2 * turn.apply(landmarks - centre) + centre + np.array([5.0, -3.0, 2.0])
        assert frame.turn_deg(landmarks, other) == pytest.approx(angle, abs=1e-3)
        assert frame.turn_deg(other, landmarks) == pytest.approx(angle, abs=1e-3)


def test_frame_round_trip_and_bad_files(frame, tmp_path):
    again = ShapeFrame.load(frame.save(tmp_path / "frame.npz"))
    np.testing.assert_array_equal(again.reference, frame.reference)
    assert again.spacing == frame.spacing
    save_arrays(tmp_path / "bad.npz", {"reference": frame.reference, "lower": frame.upper,
                "upper": frame.lower, "spacing": np.array(1.0)},
                header={"format": ShapeFrame.FORMAT, "format_version": 1})  # fmt: skip
    with pytest.raises(ModelFileError, match="inconsistent"):
        ShapeFrame.load(tmp_path / "bad.npz")
    with pytest.raises(ParameterError):
        frame.pose(frame.reference[:-1])
