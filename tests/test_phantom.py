"""The synthetic phantom cohort: determinism, pose range, ground truth, look-alike neighbours."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from medseg.datasets import make_phantom_cohort, phantom_landmark_index
from medseg.errors import ImageGeometryError
from medseg.io import physical_to_voxel, voxel_to_physical
from medseg.viz import save_slice_png


@pytest.fixture(scope="module")
def cohort():
    return make_phantom_cohort(20, random_state=7)


@pytest.fixture(scope="module")
def oblique_cohort():
    return make_phantom_cohort(3, anisotropic=True, oblique=True, random_state=11)


def _arrays(case):
    return sitk.GetArrayFromImage(case.image), sitk.GetArrayFromImage(case.label)


def test_same_seed_same_arrays_different_seed_different():
    a = make_phantom_cohort(2, random_state=3)
    b = make_phantom_cohort(2, random_state=3)
    c = make_phantom_cohort(2, random_state=4)
    for ca, cb, cc in zip(a, b, c, strict=True):
        ia, la = _arrays(ca)
        ib, lb = _arrays(cb)
        ic, lc = _arrays(cc)
        assert np.array_equal(ia, ib) and np.array_equal(la, lb)
        assert np.array_equal(ca.landmarks, cb.landmarks)
        assert ca.image.GetOrigin() == cb.image.GetOrigin()
        assert not np.array_equal(ia, ic)
        assert not np.array_equal(la, lc)
        assert not np.allclose(ca.landmarks, cc.landmarks)


def test_subject_does_not_depend_on_cohort_size():
    small = make_phantom_cohort(1, random_state=5)
    large = make_phantom_cohort(3, random_state=5)
    assert np.array_equal(_arrays(small[0])[0], _arrays(large[0])[0])


def test_cohort_structure(cohort):
    assert len(cohort) == 20
    assert cohort.labels == {"background": 0, "target": 1}
    assert len(set(cohort.subjects)) == 20
    index = cohort[0].meta["landmark_index"]
    assert len(set(index.tolist())) == 30
    for case in cohort:
        image, label = _arrays(case)
        assert image.dtype == np.float32 and label.dtype == np.uint8
        assert set(np.unique(label)) == {0, 1}
        assert np.all(np.isfinite(image))
        assert case.landmarks.shape == (30, 3)
        assert case.meta["surface_points"].shape == (2000, 3)
        np.testing.assert_array_equal(case.meta["landmark_index"], index)
        np.testing.assert_array_equal(case.landmarks, case.meta["surface_points"][index])
        # One connected target, not touching the border of the field of view.
        _, n_components = ndimage.label(label)
        assert n_components == 1
        zyx = np.argwhere(label)
        assert zyx.min() >= 2 and np.all(zyx.max(axis=0) <= np.array(label.shape) - 3)


def test_pose_range(cohort):
    angles, scales = [], []
    for case in cohort:
        pose = case.meta["pose"]
        rotation = pose["rotation"]
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        angles.append(np.rad2deg(Rotation.from_matrix(rotation).magnitude()))
        scales.append(pose["scale"])
    assert max(angles) >= 25.0
    assert max(angles) <= 30.0 + 1e-9
    assert min(scales) >= 0.8 and max(scales) <= 1.25
    assert max(scales) / min(scales) > 1.3  # the range is actually used
    # Rotation axes are spread, not one fixed axis.
    axes = [Rotation.from_matrix(c.meta["pose"]["rotation"]).as_rotvec() for c in cohort]
    axes = np.array([a / np.linalg.norm(a) for a in axes])
    assert np.linalg.svd(axes, compute_uv=False)[-1] > 1.0


def test_image_reflects_pose(cohort):
    """The label's long axis and size follow the recorded pose of the canonical shape."""
    for case in cohort:
        _, label = _arrays(case)
        voxels = voxel_to_physical(case.image, np.argwhere(label))
        pose = case.meta["pose"]
        canonical = case.meta["canonical_points"]
        axis_canonical = np.linalg.svd(canonical - canonical.mean(0), full_matrices=False)[2][0]
        axis_label = np.linalg.svd(voxels - voxels.mean(0), full_matrices=False)[2][0]
        predicted = pose["rotation"] @ axis_canonical
        assert abs(predicted @ axis_label) > np.cos(np.deg2rad(5.0))
    # Volume scales with scale**3 (shape modes add spread, so compare the extremes).
    scales = np.array([c.meta["pose"]["scale"] for c in cohort])
    volumes = np.array([_arrays(c)[1].sum() for c in cohort])
    assert volumes[np.argmax(scales)] > volumes[np.argmin(scales)]


def _mixed_neighbourhood(label: np.ndarray, zyx: np.ndarray) -> np.ndarray:
    """Whether the 3x3x3 voxels around each continuous index hold both labels."""
    centre = np.round(zyx).astype(int)
    inside = ndimage.maximum_filter(label, size=3)
    outside = ndimage.minimum_filter(label, size=3)
    z, y, x = centre.T
    return (inside[z, y, x] == 1) & (outside[z, y, x] == 0)


@pytest.mark.parametrize("which", ["isotropic", "oblique_anisotropic"])
def test_landmarks_and_surface_points_on_label_boundary(which, cohort, oblique_cohort):
    cases = list(cohort)[:5] if which == "isotropic" else list(oblique_cohort)
    for case in cases:
        _, label = _arrays(case)
        spacing_zyx = np.asarray(case.image.GetSpacing())[::-1]
        for points in (case.landmarks, case.meta["surface_points"]):
            zyx = physical_to_voxel(case.image, points)
            assert np.all(_mixed_neighbourhood(label, zyx))
        # Distance from each landmark to the label surface: the faces between 6-adjacent
        # voxels of different label, represented by their centres.
        faces = []
        for axis in range(3):
            changes = np.diff(label.astype(np.int8), axis=axis) != 0
            centres = np.argwhere(changes).astype(float)
            centres[:, axis] += 0.5
            faces.append(centres)
        tree = cKDTree(np.vstack(faces) * spacing_zyx)
        dist, _ = tree.query(physical_to_voxel(case.image, case.landmarks) * spacing_zyx)
        assert dist.max() < spacing_zyx.max()
        assert dist.mean() < 0.5 * spacing_zyx.max()


def test_landmarks_in_correspondence_spread_over_surface(cohort):
    index = phantom_landmark_index(30, 2000)
    canonical = cohort[0].meta["canonical_points"]
    # Even spread: the landmark nearest-neighbour distances vary little.
    nn, _ = cKDTree(canonical[index]).query(canonical[index], k=2)
    assert nn[:, 1].min() > 0.5 * nn[:, 1].max()
    # Same parametric sites: after undoing each pose the landmarks of two subjects differ
    # only by the (small, smooth) shape modes, far less than the landmark spacing.
    a, b = (c.meta["canonical_points"][index] for c in cohort[:2])
    assert np.median(np.linalg.norm(a - b, axis=1)) < 0.5 * np.median(nn[:, 1])


def test_shape_has_no_mirror_symmetry():
    """Reflecting the mean shape through any plane by its centroid never maps it onto itself."""
    cohort = make_phantom_cohort(1, shape_variation=0.0, random_state=0)
    points = cohort[0].meta["canonical_points"]
    points = points - points.mean(0)
    tree = cKDTree(points)
    scale = np.sqrt((points**2).sum(1).mean())
    rng = np.random.default_rng(0)
    normals = np.vstack([np.eye(3), rng.normal(size=(200, 3))])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    residuals = []
    for n in normals:
        mirrored = points - 2.0 * np.outer(points @ n, n)
        residuals.append(tree.query(mirrored)[0].mean())
    assert min(residuals) > 0.03 * scale


def test_neighbours_touch_target_with_near_equal_intensity(cohort):
    """Contrast across the boundary is small where a neighbour touches, large elsewhere."""
    fractions = []
    for case in list(cohort)[:6]:
        image, label = _arrays(case)
        label = label.astype(bool)
        spacing_zyx = np.asarray(case.image.GetSpacing())[::-1]
        d_out = ndimage.distance_transform_edt(~label, sampling=spacing_zyx)
        d_in = ndimage.distance_transform_edt(label, sampling=spacing_zyx)
        contact = case.meta["contact"]
        fractions.append(contact.mean())
        tree = cKDTree(case.meta["surface_points"])
        means = {}
        for side, distance in (("out", d_out), ("in", d_in)):
            shell = (distance >= 1.0) & (distance <= 2.5)
            _, nearest = tree.query(voxel_to_physical(case.image, np.argwhere(shell)))
            touching = contact[nearest]
            values = image[shell]
            means[side] = values[touching].mean(), values[~touching].mean()
        target = means["in"][1]
        contrast_contact = abs(means["in"][0] - means["out"][0]) / target
        contrast_elsewhere = abs(means["in"][1] - means["out"][1]) / target
        assert contrast_contact < 0.1
        assert contrast_elsewhere > 0.25
        assert contrast_contact < 0.3 * contrast_elsewhere
        ratios = np.asarray(case.meta["neighbour_intensity_ratio"])
        assert np.all(np.abs(ratios - 1.0) <= 0.1)
    assert 0.15 < np.mean(fractions) < 0.7


def test_anisotropic_and_oblique_geometry(oblique_cohort):
    for case in oblique_cohort:
        assert case.image.GetSpacing() == (1.0, 1.0, 2.0)
        assert case.image.GetSize() == (64, 64, 32)
        assert case.label.GetSpacing() == case.image.GetSpacing()
        assert case.label.GetDirection() == case.image.GetDirection()
        direction = np.asarray(case.image.GetDirection()).reshape(3, 3)
        np.testing.assert_allclose(direction @ direction.T, np.eye(3), atol=1e-12)
        assert not np.allclose(direction, np.eye(3), atol=0.1)
    plain = make_phantom_cohort(1, random_state=11)
    assert plain[0].image.GetSpacing() == (1.0, 1.0, 1.0)
    assert plain[0].image.GetDirection() == tuple(np.eye(3).ravel())


def test_invalid_arguments():
    with pytest.raises(ValueError, match="n_subjects"):
        make_phantom_cohort(0)
    with pytest.raises(ValueError, match="n_landmarks"):
        make_phantom_cohort(1, n_landmarks=2)
    with pytest.raises(ValueError, match="scale_range"):
        make_phantom_cohort(1, scale_range=(1.2, 0.9))


def test_save_slice_png(cohort, tmp_path):
    import matplotlib.image

    case = cohort[0]
    out = save_slice_png(case.image, case.label, tmp_path / "slice.png", axis=1)
    assert out == tmp_path / "slice.png"
    pixels = matplotlib.image.imread(out)
    assert pixels.ndim == 3 and pixels.shape[1] > 2 * pixels.shape[0]  # three panels
    assert pixels[..., :3].std() > 0.05
    assert sorted(p.name for p in tmp_path.iterdir()) == ["slice.png"]  # nothing left behind
    # Landmarks near the slice are drawn on top: the picture changes.
    marked = save_slice_png(
        case.image, case.label, tmp_path / "marked.png", axis=1, landmarks=case.landmarks
    )
    assert not np.array_equal(matplotlib.image.imread(marked), pixels)
    flat = sitk.Image([8, 8], sitk.sitkFloat32)
    with pytest.raises(ImageGeometryError, match="3D"):
        save_slice_png(flat, None, tmp_path / "flat.png")
    with pytest.raises(ValueError, match="index"):
        save_slice_png(case.image, case.label, tmp_path / "bad.png", index=500)
