"""Thin-plate-spline reconstruction: exactness on affine maps, geometry of the output."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from medseg.errors import ImageGeometryError, LabelError
from medseg.io import image_geometry, voxel_to_physical
from medseg.reconstruction import ThinPlateSpline, warp_labels, warp_mask, warp_surface


def _grid(size_xyz, spacing, origin, rotation=None) -> sitk.Image:
    image = sitk.Image([int(s) for s in size_xyz], sitk.sitkUInt8)
    image.SetSpacing([float(s) for s in spacing])
    image.SetOrigin([float(o) for o in origin])
    if rotation is not None:
        image.SetDirection(rotation.as_matrix().ravel().tolist())
    return image


def _ellipsoid_mask(grid: sitk.Image, centre, radii, rotation=None) -> sitk.Image:
    """Rasterise an ellipsoid (physical mm) on ``grid`` by testing voxel centres."""
    zyx = np.argwhere(np.ones(grid.GetSize()[::-1], dtype=bool))
    rotation = np.eye(3) if rotation is None else rotation
    local = (voxel_to_physical(grid, zyx) - centre) @ rotation
    inside = ((local / radii) ** 2).sum(1) <= 1.0
    mask = sitk.GetImageFromArray(inside.reshape(grid.GetSize()[::-1]).astype(np.uint8))
    mask.CopyInformation(grid)
    return mask


def _dice(a: sitk.Image, b: sitk.Image) -> float:
    x, y = sitk.GetArrayFromImage(a) > 0, sitk.GetArrayFromImage(b) > 0
    return 2.0 * (x & y).sum() / (x.sum() + y.sum())


RADII = np.array([12.0, 8.0, 6.0])


@pytest.fixture(scope="module")
def template():
    grid = _grid((40, 34, 30), (1.0, 1.0, 1.0), (-20.0, -17.0, -15.0))
    mask = _ellipsoid_mask(grid, np.zeros(3), RADII)
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(24, 3))
    # points on the ellipsoid surface: scale each direction so that |x / radii| = 1
    landmarks = directions / np.linalg.norm(directions / RADII, axis=1, keepdims=True)
    return mask, landmarks


def test_tps_reproduces_a_similarity_transform_exactly():
    rng = np.random.default_rng(1)
    source = rng.normal(size=(10, 3)) * 10
    rot = Rotation.from_euler("xyz", [30, -20, 40], degrees=True).as_matrix()
    target = 1.2 * source @ rot.T + [5.0, -3.0, 2.0]
    tps = ThinPlateSpline(source, target)
    probe = rng.normal(size=(50, 3)) * 15
    np.testing.assert_allclose(tps(probe), 1.2 * probe @ rot.T + [5.0, -3.0, 2.0], atol=1e-6)


def test_tps_interpolates_landmarks_and_smoothing_relaxes_it():
    rng = np.random.default_rng(2)
    source = rng.normal(size=(12, 3)) * 10
    target = source + rng.normal(size=(12, 3))
    np.testing.assert_allclose(ThinPlateSpline(source, target)(source), target, atol=1e-6)
    smooth = ThinPlateSpline(source, target, smoothing=100.0)(source)
    assert np.abs(smooth - target).max() > 0.1


def test_identity_warp_returns_the_template(template):
    mask, landmarks = template
    out = warp_mask(mask, landmarks, landmarks, mask)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(out), sitk.GetArrayFromImage(mask))


def test_warped_labels_keep_their_values_and_the_union_of_warp_mask(template):
    mask, landmarks = template
    arr = sitk.GetArrayFromImage(mask)
    x = np.arange(arr.shape[2])[None, None, :]
    labels = sitk.GetImageFromArray((arr * np.where(x < arr.shape[2] // 2, 1, 2)).astype(np.uint8))
    labels.CopyInformation(mask)
    same = warp_labels(labels, landmarks, landmarks, mask)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(same), sitk.GetArrayFromImage(labels))
    # moved and rotated onto another grid: the union is warp_mask's, both halves survive
    rotation = Rotation.from_euler("xyz", [20, -10, 35], degrees=True)
    grid = _grid((50, 44, 40), (0.8, 1.1, 1.3), (-22.0, -20.0, -18.0), rotation)
    moved = landmarks @ rotation.as_matrix().T + [1.5, -2.0, 0.5]
    out = sitk.GetArrayFromImage(warp_labels(labels, landmarks, moved, grid))
    union = sitk.GetArrayFromImage(warp_mask(mask, landmarks, moved, grid))
    np.testing.assert_array_equal(out > 0, union > 0)
    assert set(np.unique(out)) == {0, 1, 2}
    assert abs(int((out == 1).sum()) - int((out == 2).sum())) < 0.1 * (out > 0).sum()


def test_warp_onto_oblique_anisotropic_grid_follows_the_similarity(template):
    mask, landmarks = template
    rot = Rotation.from_euler("zyx", [35, 20, -25], degrees=True)
    scale, shift = 1.15, np.array([4.0, -6.0, 3.0])
    moved = scale * landmarks @ rot.as_matrix().T + shift
    reference = _grid(
        (48, 44, 22),
        (0.9, 1.1, 2.2),
        shift - [20.0, 22.0, 22.0],
        rotation=Rotation.from_euler("z", 12, degrees=True),
    )
    out = warp_mask(mask, landmarks, moved, reference)

    assert image_geometry(out) == image_geometry(reference)
    assert out.GetPixelID() == sitk.sitkUInt8
    truth = _ellipsoid_mask(reference, shift, scale * RADII, rot.as_matrix())
    assert _dice(out, truth) > 0.93


def test_warp_outside_the_field_of_view_is_empty(template):
    mask, landmarks = template
    reference = _grid((10, 10, 10), (1.0, 1.0, 1.0), (200.0, 200.0, 200.0))
    out = warp_mask(mask, landmarks, landmarks, reference)
    assert image_geometry(out) == image_geometry(reference)
    assert sitk.GetArrayViewFromImage(out).max() == 0


def test_warp_surface_maps_vertices_in_mm(template):
    _, landmarks = template
    rot = Rotation.from_euler("xyz", [10, 50, -30], degrees=True).as_matrix()
    moved = 0.9 * landmarks @ rot.T + 7.0
    vertices = np.array([[12.0, 0, 0], [0, 8.0, 0], [0, 0, 6.0], [-12.0, 0, 0]])
    faces = np.array([[0, 1, 2], [1, 2, 3]])
    surface = warp_surface(vertices, faces, landmarks, moved)
    np.testing.assert_allclose(surface.points, 0.9 * vertices @ rot.T + 7.0, atol=1e-6)
    assert surface.n_cells == 2


def test_bad_input_is_a_clear_error(template):
    mask, landmarks = template
    flat = landmarks.copy()
    flat[:, 2] = 0.0
    with pytest.raises(ImageGeometryError, match="coplanar"):
        ThinPlateSpline(flat, flat)
    with pytest.raises(ImageGeometryError, match="differ in shape"):
        ThinPlateSpline(landmarks, landmarks[:-1])
    bad = landmarks.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ImageGeometryError, match="NaN"):
        warp_mask(mask, landmarks, bad, mask)
    empty = sitk.Image(mask.GetSize(), sitk.sitkUInt8)
    empty.CopyInformation(mask)
    with pytest.raises(LabelError, match="empty"):
        warp_mask(empty, landmarks, landmarks, mask)
