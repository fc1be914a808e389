"""The active shape model baseline: point distribution model, landmark mesh, search."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from medseg.datasets import Cohort, make_phantom_cohort
from medseg.errors import CohortError, ModelFileError, NotFittedError
from medseg.evaluation.baselines import ASMBaseline
from medseg.evaluation.metrics import dice, landmark_errors
from medseg.geometry import vertex_normals
from medseg.io import load_arrays, save_arrays, select_labels, voxel_to_physical
from medseg.shape import ActiveShapeModel, landmark_mesh, point_distribution_model


def _sphere_points(n: int) -> np.ndarray:
    m = np.arange(n) + 0.5
    z = 1 - 2 * m / n
    phi = np.pi * (1 + 5**0.5) * m
    r = np.sqrt(1 - z**2)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _random_pose(points, rng):
    rot = Rotation.random(random_state=rng).as_matrix()
    return rng.uniform(0.5, 2.0) * points @ rot.T + rng.uniform(-20, 20, 3)


def _shapes_with_two_modes(rng, n_shapes=30, n_points=40):
    base = _sphere_points(n_points) * np.array([3.0, 2.0, 1.0])
    mode1 = np.zeros_like(base)
    mode1[:, 0] = base[:, 0] * np.abs(base[:, 1])  # bulge, not a similarity
    mode2 = np.zeros_like(base)
    mode2[:, 2] = base[:, 2] * base[:, 0]  # twist-like shear along x
    a = rng.standard_normal((n_shapes, 2)) * np.array([0.20, 0.08])
    shapes = base + a[:, :1, None] * mode1 + a[:, 1:, None] * mode2
    return shapes, (mode1, mode2)


def test_pdm_is_pose_invariant_and_finds_the_generating_modes():
    rng = np.random.RandomState(0)
    shapes, _ = _shapes_with_two_modes(rng)
    pdm = point_distribution_model(shapes, variance=0.98)
    posed = np.stack([_random_pose(s, rng) for s in shapes])
    pdm_posed = point_distribution_model(posed, variance=0.98)

    # Two non-rigid degrees of freedom generated the shapes: with alignment working, two
    # modes explain 98 % even of randomly posed copies (a leftover pose adds modes).
    assert pdm.modes.shape[0] == 2 and pdm_posed.modes.shape[0] == 2
    np.testing.assert_allclose(pdm_posed.eigenvalues, pdm.eigenvalues, rtol=1e-6)
    flat = pdm.modes.reshape(len(pdm.modes), -1)
    np.testing.assert_allclose(flat @ flat.T, np.eye(len(flat)), atol=1e-10)
    assert np.all(np.diff(pdm.eigenvalues) <= 0)
    assert pdm.explained >= 0.98
    assert np.linalg.norm(pdm.mean) == pytest.approx(1.0)
    np.testing.assert_allclose(pdm.mean.mean(axis=0), 0.0, atol=1e-12)
    # Fewer modes would not reach 98 %.
    assert (
        pdm.eigenvalues[:-1].sum()
        / (np.var((pdm.aligned - pdm.mean).reshape(len(shapes), -1), axis=0, ddof=1).sum())
        < 0.98
    )


def test_landmark_mesh_is_a_closed_outward_surface():
    points = _sphere_points(60) * np.array([3.0, 1.5, 1.0])
    faces = landmark_mesh(points)
    assert set(np.unique(faces)) == set(range(len(points)))
    edges = {tuple(sorted(e)) for f in faces for e in ((f[0], f[1]), (f[1], f[2]), (f[0], f[2]))}
    assert len(points) - len(edges) + len(faces) == 2  # Euler characteristic of a sphere
    normals = vertex_normals(points, faces)
    radial = points / np.linalg.norm(points, axis=1, keepdims=True)
    assert np.all(np.einsum("ij,ij->i", normals, radial) > 0.3)
    # Normals follow a rotated instance.
    rot = Rotation.from_euler("xyz", [30, -20, 50], degrees=True).as_matrix()
    np.testing.assert_allclose(vertex_normals(points @ rot.T, faces), normals @ rot.T, atol=1e-12)


@pytest.fixture(scope="module")
def phantom():
    return make_phantom_cohort(9, size=56, random_state=3)


def test_asm_search_moves_from_its_start_onto_the_structure(phantom):
    train, test = phantom[list(range(8))], phantom[8]
    asm = ASMBaseline().fit(train)
    assert asm.model_.modes_.shape[1:] == (30, 3) and 1 <= len(asm.model_.eigenvalues_) <= 7
    # Move the structure 5.4 mm away from the image centre, where the search starts.
    shift = np.array([4.0, -3.0, 2.0])
    moved = sitk.TranslationTransform(3, (-shift).tolist())  # output -> input points
    image = sitk.Resample(test.load_image(), moved, sitk.sitkLinear, 50.0)
    reference = sitk.Resample(
        select_labels(test.load_label(), (1,)), moved, sitk.sitkNearestNeighbor, 0
    )
    truth = test.landmarks + shift
    result = asm.segment(image)

    size_zyx = np.asarray(image.GetSize(), float)[::-1]
    centre = voxel_to_physical(image, ((size_zyx - 1) / 2)[None])[0]
    start = asm.model_.mean_size_ * asm.model_.mean_shape_ + centre
    start_error = landmark_errors(start, truth)[0].mean()
    error = landmark_errors(result.landmarks, truth)[0].mean()
    assert start_error > 5.0
    assert error < 0.5 * start_error  # the search pulled the model onto the structure
    assert dice(result.label, reference) > 0.6
    for attr in ("GetSize", "GetSpacing", "GetOrigin", "GetDirection"):
        assert getattr(result.label, attr)() == getattr(image, attr)()
    # Shape parameters stay within +-3 sqrt(lambda); the search is deterministic.
    assert np.all(np.abs(result.shape_parameters) <= 3 * np.sqrt(asm.model_.eigenvalues_) + 1e-12)
    again = asm.segment(image)
    np.testing.assert_array_equal(again.landmarks, result.landmarks)
    assert sitk.GetArrayViewFromImage(result.label).any()


def test_asm_bad_use(phantom):
    with pytest.raises(NotFittedError, match="fit"):
        ASMBaseline().segment(phantom[0].load_image())
    without = Cohort(
        cases=[
            type(c)(c.case_id, c.subject, c.image, c.label, None) for c in phantom[list(range(4))]
        ]
    )
    with pytest.raises(CohortError, match="no landmarks"):
        ASMBaseline().fit(without)
    with pytest.raises(CohortError, match="at least 3"):
        ASMBaseline().fit(phantom[[0, 1]])


@pytest.fixture(scope="module")
def shape_model(phantom):
    train = phantom[list(range(8))]
    images = [c.load_image() for c in train]
    return ActiveShapeModel().fit(np.stack([c.load_landmarks() for c in train]), images)


def test_search_from_a_nearby_start_moves_it_onto_the_boundary(phantom, shape_model):
    """The segmenter's refinement: a start a few mm off (pose and noise) is pulled in."""
    test = phantom[8]
    truth = test.load_landmarks()
    rng = np.random.RandomState(0)
    rot = Rotation.from_rotvec(np.deg2rad(8.0) * np.array([0.3, 0.8, -0.5])).as_matrix()
    centroid = truth.mean(0)
    start = (truth - centroid) @ rot.T + centroid + [1.5, -1.0, 1.0]
    start = start + rng.normal(scale=1.0, size=start.shape)
    found = shape_model.search(test.load_image(), start=start, levels=2)
    start_error = landmark_errors(start, truth)[0].mean()
    error = landmark_errors(found.landmarks, truth)[0].mean()
    assert start_error > 2.5
    assert error < 0.6 * start_error
    assert len(found.n_iter) == 2
    # the profile cost tells the boundary from a configuration 3 mm outside it
    assert found.profile_cost == pytest.approx(
        shape_model.profile_cost(test.load_image(), found.landmarks)
    )
    outside = truth + 3.0 * vertex_normals(truth, shape_model.faces_)
    image = test.load_image()
    assert shape_model.profile_cost(image, truth) < 0.5 * shape_model.profile_cost(image, outside)
    with pytest.raises(ValueError, match="start"):
        shape_model.search(test.load_image(), start=start[:-1])


def test_active_shape_model_save_load_round_trip(phantom, shape_model, tmp_path):
    again = ActiveShapeModel.load(shape_model.save(tmp_path / "asm.npz"))
    image = phantom[8].load_image()
    expected = shape_model.search(image).landmarks
    np.testing.assert_array_equal(again.search(image).landmarks, expected)
    header, arrays = load_arrays(tmp_path / "asm.npz", what="test")
    arrays["profile_means"] = arrays["profile_means"][:, :-1]
    save_arrays(tmp_path / "broken.npz", arrays, header=header)
    with pytest.raises(ModelFileError, match="inconsistent"):
        ActiveShapeModel.load(tmp_path / "broken.npz")
    with pytest.raises(NotFittedError):
        ActiveShapeModel().save(tmp_path / "unfitted.npz")


def test_training_costs_are_each_training_shape_on_its_own_image(phantom, shape_model, tmp_path):
    """The scale a search's cost is judged on: the profile cost of every training shape."""
    train = phantom[list(range(8))]
    expected = [shape_model.profile_cost(c.load_image(), c.load_landmarks()) for c in train]
    np.testing.assert_allclose(shape_model.training_costs_, expected, rtol=1e-12)
    # a held-out case at its truth fits worse than the training shapes do on average
    held_out = shape_model.profile_cost(phantom[8].load_image(), phantom[8].load_landmarks())
    assert held_out > np.mean(expected)
    again = ActiveShapeModel.load(shape_model.save(tmp_path / "asm.npz"))
    np.testing.assert_array_equal(again.training_costs_, shape_model.training_costs_)
    # a file of format version 1 has none, and says so; saved again it stays version 1
    header, arrays = load_arrays(tmp_path / "asm.npz", what="test")
    assert header["format_version"] == 2
    del arrays["training_costs"]
    save_arrays(tmp_path / "v1.npz", arrays, header=header | {"format_version": 1})
    old = ActiveShapeModel.load(tmp_path / "v1.npz")
    assert old.training_costs_ is None
    np.testing.assert_array_equal(
        old.search(phantom[8].load_image()).landmarks,
        shape_model.search(phantom[8].load_image()).landmarks,
    )
    header, _ = load_arrays(old.save(tmp_path / "v1_again.npz"), what="test")
    assert header["format_version"] == 1
    arrays["training_costs"] = np.array([1.0, np.nan])
    save_arrays(tmp_path / "nan.npz", arrays, header=header)
    with pytest.raises(ModelFileError, match="inconsistent"):
        ActiveShapeModel.load(tmp_path / "nan.npz")


def test_asm_with_the_regional_stage_refines_its_own_shape_only_map(phantom):
    train, test = phantom[list(range(8))], phantom[8]
    asm = ASMBaseline(boundary=True, random_state=0).fit(train)
    assert asm.boundary_ is not None and asm.frame_ is not None
    result = asm.segment(test.load_image())
    plain = ASMBaseline().fit(train).segment(test.load_image())
    # the shape-only map is the plain ASM's; the refined one its own, on the same grid
    np.testing.assert_array_equal(
        sitk.GetArrayFromImage(result.shape_label), sitk.GetArrayFromImage(plain.label)
    )
    assert result.label.GetSize() == result.shape_label.GetSize()
    assert "boundary" in result.timings
    reference = select_labels(test.load_label(), (1,))
    assert dice(result.label, reference) > 0.5
