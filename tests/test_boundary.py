"""The regional stage: a voxel classifier and a graph cut in the shape's frame.

On generated ellipsoids of two sub-labels with a known boundary: the stage moves a
misplaced template back onto the image, keeps the sub-labels, and answers in the input's
exact geometry whatever its spacing and direction.
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage

from medseg.errors import ModelFileError
from medseg.frame import ShapeFrame
from medseg.io import label_values, resample_like
from medseg.reconstruction import warp_labels
from medseg.segmenter._boundary import BoundaryStage
from medseg.segmenter._frame_view import signed_distance

SIZE = 40


def _directions(n: int = 24) -> np.ndarray:
    """Fibonacci points on the unit sphere: the landmarks' directions, in correspondence."""
    k = np.arange(n) + 0.5
    polar = np.arccos(1 - 2 * k / n)
    azimuth = np.pi * (1 + 5**0.5) * k
    return np.stack(
        [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1
    )


def _case(seed: int):
    """An ellipsoid (label 1 where x < its centre, 2 beyond) in noise; its landmarks."""
    rng = np.random.default_rng(seed)
    radii = np.array([10.0, 7.0, 5.5]) * rng.uniform(0.9, 1.1)
    centre = SIZE / 2 + rng.uniform(-2, 2, 3)
    z, y, x = np.mgrid[:SIZE, :SIZE, :SIZE].astype(float)
    q = sum(((c - m) / r) ** 2 for c, m, r in zip((x, y, z), centre, radii, strict=True))
    inside = q <= 1
    labels = np.where(inside, np.where(x < centre[0], 1, 2), 0).astype(np.uint8)
    values = 40 + 60 * ndimage.gaussian_filter(inside.astype(float), 0.7)
    # a bright distractor touching the structure, so that edges alone do not decide
    values += 50 * (np.abs(x - centre[0] - radii[0] - 3) < 1.5)
    values += rng.normal(0, 6, values.shape)
    image = sitk.GetImageFromArray(values.astype(np.float32))
    label = sitk.GetImageFromArray(labels)
    label.CopyInformation(image)
    return image, label, centre + radii * _directions()


@pytest.fixture(scope="module")
def cohort():
    return [_case(seed) for seed in range(12)]


@pytest.fixture(scope="module")
def stage(cohort):
    train = cohort[:10]
    images, labels, landmarks = zip(*train, strict=True)
    frame = ShapeFrame.fit(np.stack(landmarks), list(images))
    template = (labels[0], landmarks[0])
    fitted = BoundaryStage(
        n_estimators=10,
        rows_per_case=3000,
        smoothness=(0.5, 2.0),
        shape_weight=(0.0, 0.3),
        validation_fraction=0.5,  # 5 cases: as many as the quality score needs
        random_state=0,
    ).fit(frame, *template, list(images), list(labels), np.stack(landmarks))
    return fitted, frame, template


def _centroid(label: sitk.Image) -> np.ndarray:
    index = np.argwhere(sitk.GetArrayViewFromImage(label) > 0)[:, ::-1].astype(float)
    return np.mean([label.TransformContinuousIndexToPhysicalPoint(p.tolist()) for p in index], 0)


def _dice(a: np.ndarray, b: np.ndarray) -> float:
    return 2.0 * np.logical_and(a, b).sum() / (a.sum() + b.sum())


def test_a_template_shifted_by_two_voxels_comes_back_within_one(stage, cohort):
    fitted, frame, template = stage
    image, truth, landmarks = cohort[10]
    shift = np.array([2.0, 0.0, 0.0])  # mm, 2 voxels, along the long axis
    shape_only = warp_labels(*template, landmarks + shift, image)
    refined = fitted.refine(frame, *template, image, landmarks + shift).label
    assert refined.GetSize() == image.GetSize()
    true_centre = _centroid(truth)
    # the shape-only map is off by the shift; the refined one within a voxel of the truth
    assert np.linalg.norm(_centroid(shape_only) - true_centre) > 1.5
    assert np.linalg.norm(_centroid(refined) - true_centre) < 1.0
    t = sitk.GetArrayViewFromImage(truth) > 0
    assert _dice(sitk.GetArrayViewFromImage(refined) > 0, t) > _dice(
        sitk.GetArrayViewFromImage(shape_only) > 0, t
    )
    # boundary voxels within one voxel of the true boundary, on average
    d = np.abs(signed_distance(t, (1.0, 1.0, 1.0)))
    border = sitk.GetArrayFromImage(sitk.LabelContour(refined > 0)) > 0
    assert d[border].mean() < 1.0


def test_sub_labels_come_back_in_an_oblique_anisotropic_geometry(stage, cohort):
    fitted, frame, template = stage
    image, truth, landmarks = cohort[11]
    angle = np.deg2rad(25.0)
    axis = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    rotation = sitk.VersorTransform(axis.tolist(), angle).GetMatrix()
    spacing = (0.8, 1.3, 1.1)
    size = [int(np.ceil(SIZE / s)) for s in spacing]
    grid = sitk.Image(size, sitk.sitkUInt8)
    grid.SetSpacing(spacing)
    grid.SetDirection(rotation)
    half = np.asarray(rotation).reshape(3, 3) @ (np.asarray(size) * spacing / 2)
    grid.SetOrigin((np.full(3, SIZE / 2) - half).tolist())
    oblique = resample_like(image, grid, is_label=False)
    oblique_truth = sitk.GetArrayFromImage(resample_like(truth, grid, is_label=True))
    refined = fitted.refine(frame, *template, oblique, landmarks).label
    for name in ("GetSize", "GetSpacing", "GetOrigin", "GetDirection"):
        assert getattr(refined, name)() == getattr(oblique, name)()
    out = sitk.GetArrayFromImage(refined)
    assert set(np.unique(out)) == {0, 1, 2}
    for value in (1, 2):
        assert _dice(out == value, oblique_truth == value) > 0.85


def test_weights_are_chosen_on_held_out_cases_and_the_stage_round_trips(stage, cohort, tmp_path):
    fitted, frame, template = stage
    assert len(fitted.selection_) == 4
    best = max(fitted.selection_, key=lambda row: row[2])
    assert (fitted.smoothness_, fitted.shape_weight_) == best[:2]
    assert fitted.values_ == (1, 2)
    again = BoundaryStage.load(fitted.save(tmp_path / "boundary"))
    image, _, landmarks = cohort[10]
    a, b = (s.refine(frame, *template, image, landmarks) for s in (again, fitted))
    np.testing.assert_array_equal(sitk.GetArrayFromImage(a.label), sitk.GetArrayFromImage(b.label))
    assert a.score == b.score and np.isfinite(a.score)
    (tmp_path / "boundary" / "stage.npz").write_bytes(b"not an archive")
    with pytest.raises(ModelFileError):
        BoundaryStage.load(tmp_path / "boundary")


def test_a_template_on_the_wrong_place_scores_as_a_failure(stage, cohort):
    fitted, frame, template = stage
    image, _, landmarks = cohort[10]
    right = fitted.refine(frame, *template, image, landmarks)
    # the shape moved half its length along its axis: half of it on background
    wrong = fitted.refine(frame, *template, image, landmarks + np.array([9.0, 0.0, 0.0]))
    assert wrong.disagreement > right.disagreement and wrong.change > right.change
    assert right.score < 3.0 < wrong.score


def test_label_values_keep_several_labels_and_binarise_one():
    arr = np.array([[[0, 1, 2, 3]]], dtype=np.uint8)
    image = sitk.GetImageFromArray(arr)
    assert sitk.GetArrayFromImage(label_values(image, (1, 2))).ravel().tolist() == [0, 1, 2, 0]
    assert sitk.GetArrayFromImage(label_values(image, (3,))).ravel().tolist() == [0, 0, 0, 1]


def test_signed_distance_is_negative_inside_and_metric():
    mask = np.zeros((1, 1, 9), dtype=bool)
    mask[0, 0, 3:6] = True
    d = signed_distance(mask, (1.0, 1.0, 2.0))
    assert np.all(d[mask] < 0) and np.all(d[~mask] > 0)
    # 3 voxels of 2 mm beyond the last inside voxel, less half the smallest spacing
    assert d[0, 0, 8] == pytest.approx(3 * 2.0 - 0.5)
