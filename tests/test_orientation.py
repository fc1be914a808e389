"""The handedness term: triangles against boundary directions, and where those come from."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from medseg.detection import gradient_directions
from medseg.errors import MedsegError, ModelFileError, NotFittedError
from medseg.io import load_arrays, save_arrays, voxel_to_physical
from medseg.shape import OrientationPrior, select_cliques, triangle_orientation

REFLECT = np.diag([-1.0, 1.0, 1.0])


def _ellipsoid_shapes(n_shapes: int, seed: int):
    """The same 14 sites on random ellipsoids in random poses, with their outward normals."""
    base = np.random.default_rng(123).normal(size=(14, 3))
    rng = np.random.default_rng(seed)
    base /= np.linalg.norm(base, axis=1, keepdims=True)
    shapes, normals = [], []
    for _ in range(n_shapes):
        axes = np.array([20.0, 12.0, 8.0]) * rng.uniform(0.9, 1.1, 3)
        pts = base * axes
        nrm = base / axes  # gradient of sum((x / a)^2)
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        rot = Rotation.random(random_state=rng).as_matrix()
        scale = rng.uniform(0.8, 1.25)
        shapes.append(scale * pts @ rot.T + rng.normal(scale=5.0, size=3))
        normals.append(nrm @ rot.T)
    return np.array(shapes), np.array(normals)


def test_triangle_orientation_is_pose_invariant_and_flips_under_reflection():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 3, 3))
    g = rng.normal(size=(50, 3, 3))
    cos = triangle_orientation(*x.transpose(1, 0, 2), *g.transpose(1, 0, 2))
    rot = Rotation.random(random_state=1).as_matrix()
    moved = 2.5 * x @ rot.T + np.array([3.0, -1.0, 7.0])
    np.testing.assert_allclose(
        triangle_orientation(*moved.transpose(1, 0, 2), *(g @ rot.T).transpose(1, 0, 2)),
        cos,
        atol=1e-12,
    )
    mirrored = triangle_orientation(
        *(x @ REFLECT).transpose(1, 0, 2), *(g @ REFLECT).transpose(1, 0, 2)
    )
    np.testing.assert_allclose(mirrored, -cos, atol=1e-12)
    assert np.all(np.abs(cos) <= 1 + 1e-12)
    # a degenerate triangle has no orientation
    flat = np.zeros((3, 3))
    assert triangle_orientation(flat[0], flat[1], flat[2], g[0, 0], g[0, 1], g[0, 2]) == 0.0


def test_orientation_prior_penalises_the_mirror_labelling_only():
    shapes, normals = _ellipsoid_shapes(12, seed=0)
    cliques = select_cliques(shapes[0], method="knn")
    prior = OrientationPrior().fit(shapes, normals, cliques=cliques)
    # most cliques face the same way in all 12 shapes: (12 + 1) / (12 + 2) after smoothing
    assert np.median(prior.agreement_) == pytest.approx(13 / 14)
    test, test_normals = _ellipsoid_shapes(1, seed=5)
    right = prior.potentials(test[0], test_normals[0])
    mirror = prior.potentials(test[0] @ REFLECT, test_normals[0] @ REFLECT)
    # the right configuration pays for triangles that face the boundary obliquely only
    assert right.sum() < 0.3 * mirror.sum()
    assert np.mean(mirror > right) > 0.9
    # the tables hold the same potentials at the chosen candidates
    rng = np.random.default_rng(3)
    cand = test[0][:, None, :] + rng.normal(scale=2.0, size=(len(test[0]), 4, 3))
    cand[:, 2] = test[0]
    dirs = np.repeat(test_normals[0][:, None, :], 4, axis=1)
    tables = prior.tables(cand, dirs, chunk_size=5)
    i, j, k = prior.cliques_.T
    np.testing.assert_allclose(tables[np.arange(len(i)), 2, 2, 2], right, rtol=1e-5, atol=1e-6)
    one = tables[np.arange(len(i)), 0, 3, 1]
    # corners i, j, k take candidates 0, 3, 1: that configuration, clique by clique
    conf = np.array(
        [
            triangle_orientation(
                cand[a, 0], cand[b, 3], cand[c, 1], dirs[a, 0], dirs[b, 3], dirs[c, 1]
            )
            for a, b, c in prior.cliques_
        ]
    )
    manual = 0.5 * (1 - prior.reference_ * conf) * prior.penalty_
    np.testing.assert_allclose(one, manual, rtol=1e-5, atol=1e-6)
    # and every other triple (directions differing between candidates too), one candidate
    # list broadcast against the others
    dirs = rng.normal(size=dirs.shape)
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    tables = prior.tables(cand, dirs, chunk_size=5)
    every = triangle_orientation(
        cand[i][:, :, None, None], cand[j][:, None, :, None], cand[k][:, None, None, :],
        dirs[i][:, :, None, None], dirs[j][:, None, :, None], dirs[k][:, None, None, :],
    )  # fmt: skip
    ref = prior.reference_[:, None, None, None]
    expected = 0.5 * (1 - ref * every) * prior.penalty_[:, None, None, None]
    np.testing.assert_allclose(tables, expected, rtol=1e-5, atol=1e-6)


def test_orientation_prior_save_load_round_trip_and_errors(tmp_path):
    shapes, normals = _ellipsoid_shapes(6, seed=2)
    cliques = select_cliques(shapes[0], method="knn")
    with pytest.raises(NotFittedError):
        OrientationPrior().potentials(shapes[0], normals[0])
    prior = OrientationPrior().fit(shapes, normals, cliques=cliques)
    again = OrientationPrior.load(prior.save(tmp_path / "orientation.npz"))
    np.testing.assert_array_equal(
        again.potentials(shapes[1], normals[1]), prior.potentials(shapes[1], normals[1])
    )
    header, arrays = load_arrays(tmp_path / "orientation.npz", what="test")
    arrays["reference"] = arrays["reference"][:-1]
    save_arrays(tmp_path / "bad.npz", arrays, header=header)
    with pytest.raises(ModelFileError, match="inconsistent"):
        OrientationPrior.load(tmp_path / "bad.npz")
    save_arrays(tmp_path / "other.npz", arrays, header={"format": "x", "format_version": 1})
    with pytest.raises(ModelFileError, match="not a medseg.shape.OrientationPrior"):
        OrientationPrior.load(tmp_path / "other.npz")
    with pytest.raises(ValueError, match="shape"):
        OrientationPrior().fit(shapes, normals[:, :5], cliques=cliques)
    with pytest.raises(ValueError, match="indices"):
        OrientationPrior().fit(shapes, normals, cliques=cliques + 100)


def _ball_image(rotation: np.ndarray, spacing=(1.0, 1.0, 2.0)) -> sitk.Image:
    """A bright ball of radius 10 mm at the origin, on an oblique anisotropic grid."""
    size = (48, 48, 24)
    image = sitk.Image(size, sitk.sitkFloat32)
    image.SetSpacing(spacing)
    image.SetDirection(rotation.ravel().tolist())
    centre_index = (np.array(size) - 1) / 2
    image.SetOrigin((-(rotation @ (np.array(spacing) * centre_index))).tolist())
    zyx = np.argwhere(np.ones(size[::-1], bool))
    radius = np.linalg.norm(voxel_to_physical(image, zyx), axis=1).reshape(size[::-1])
    image = sitk.GetImageFromArray((100.0 / (1 + np.exp((radius - 10.0) / 0.7))).astype(np.float32))
    image.SetSpacing(spacing)
    image.SetDirection(rotation.ravel().tolist())
    image.SetOrigin((-(rotation @ (np.array(spacing) * centre_index))).tolist())
    return image


def test_gradient_directions_point_into_a_bright_ball_on_an_oblique_grid():
    rotation = Rotation.from_euler("zyx", [25, -15, 10], degrees=True).as_matrix()
    image = _ball_image(rotation)
    rng = np.random.default_rng(0)
    radial = rng.normal(size=(30, 3))
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    radial[:, 2] *= 0.4  # stay inside the thinner z extent
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    dirs = gradient_directions(image, 10.0 * radial, sigma_mm=1.0)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-9)
    cosines = np.einsum("nd,nd->n", dirs, -radial)
    assert np.median(cosines) > 0.97 and cosines.min() > 0.9


def test_gradient_directions_of_a_constant_image_are_zero_and_bad_input_is_refused():
    image = sitk.Image((10, 10, 10), sitk.sitkFloat32) + 5.0
    assert np.all(gradient_directions(image, np.zeros((2, 3))) == 0)
    # a grid thinner than a Gaussian's support still gives directions (here along z only)
    ramp = sitk.GetImageFromArray(
        np.arange(2, dtype=np.float32)[:, None, None] * np.ones((2, 3, 3))
    )
    np.testing.assert_allclose(gradient_directions(ramp, [[1.0, 1.0, 0.5]]), [[0, 0, 1]])
    with pytest.raises(MedsegError, match="3D"):
        gradient_directions(sitk.Image((10, 10), sitk.sitkFloat32), np.zeros((1, 3)))
    with pytest.raises(MedsegError, match="sigma_mm"):
        gradient_directions(image, np.zeros((1, 3)), sigma_mm=0)
