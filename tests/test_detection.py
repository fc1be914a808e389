"""Tests of medseg.detection: features, sampling, forests, candidates, persistence.

Small generated images: an asymmetric blob (ellipsoid plus a bump) in a random pose, with
landmarks at known points of its surface.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage
from scipy.spatial.transform import Rotation
from sklearn.base import BaseEstimator, clone

from medseg.detection import (
    CandidateSet,
    FeatureSettings,
    LandmarkDetector,
    compute_features,
    feature_names,
    non_maximum_suppression,
    sample_landmark_voxels,
)
from medseg.detection._context import context_features
from medseg.detection._features import _sym3_eigvals
from medseg.errors import (
    ImageGeometryError,
    InputFileError,
    LabelError,
    MedsegError,
    ModelFileError,
    NotFittedError,
    ParameterError,
    ResourceLimitError,
)
from medseg.io import physical_to_voxel, voxel_to_physical

RADII = np.array([10.0, 6.5, 5.0])
BUMP = np.array([7.0, 4.5, 0.0])


def _canonical_landmarks() -> np.ndarray:
    dirs = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    pts = dirs * RADII
    bump_tip = BUMP + 4.0 * np.array([0.6, 0.8, 0.0])
    return np.vstack([pts, bump_tip])


def make_blob(
    rng: np.random.Generator,
    *,
    size=(36, 36, 36),
    spacing=(1.0, 1.0, 1.0),
    direction=None,
    rotate=True,
):
    """A blob image in a random pose (and intensity scale) and its 7 landmarks (mm)."""
    ref = sitk.Image([int(s) for s in size[::-1]], sitk.sitkFloat32)
    ref.SetSpacing([float(s) for s in spacing])
    if direction is not None:
        ref.SetDirection([float(v) for v in np.asarray(direction).ravel()])
    centre_vox = (np.asarray(size, float) - 1) / 2
    centre = voxel_to_physical(ref, centre_vox) + rng.uniform(-1.5, 1.5, 3)
    rot = Rotation.random(random_state=rng).as_matrix() if rotate else np.eye(3)
    zyx = np.stack(np.meshgrid(*[np.arange(s) for s in size], indexing="ij"), -1).reshape(-1, 3)
    local = (voxel_to_physical(ref, zyx) - centre) @ rot
    inside = (((local / RADII) ** 2).sum(1) <= 1) | (np.linalg.norm(local - BUMP, axis=1) <= 4.0)
    scale = rng.uniform(50, 300)
    arr = np.where(inside, 1.0, 0.25).reshape(size) * scale
    arr = ndimage.gaussian_filter(arr, 0.6) + rng.normal(0, 0.04 * scale, size)
    image = sitk.GetImageFromArray(arr.astype(np.float32))
    image.CopyInformation(ref)
    return image, _canonical_landmarks() @ rot.T + centre


@pytest.fixture(scope="module")
def blobs():
    rng = np.random.default_rng(7)
    return [make_blob(rng) for _ in range(9)]


@pytest.fixture(scope="module")
def small_settings():
    return FeatureSettings(scales_mm=(1.0, 2.0, 4.0), shell_radii_mm=(3.0, 6.0))


@pytest.fixture(scope="module")
def fitted(blobs, small_settings):
    det = LandmarkDetector(
        features=small_settings,
        n_estimators=12,
        n_negative=150,
        n_mining_pool=4000,
        auto_context=True,
        random_state=0,
        n_jobs=2,
    )
    return det.fit([b[0] for b in blobs[:6]], [b[1] for b in blobs[:6]])


# ----------------------------------------------------------------------------- features
def test_sym3_eigvals_match_numpy():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(500, 3, 3))
    a = a + a.transpose(0, 2, 1)
    a[:10] = np.diag([2.0, 2.0, 2.0])  # repeated eigenvalues
    out = np.empty((500, 3))
    _sym3_eigvals(a[:, 0, 0], a[:, 0, 1], a[:, 0, 2], a[:, 1, 1], a[:, 1, 2], a[:, 2, 2], out)
    np.testing.assert_allclose(out, np.linalg.eigvalsh(a), atol=1e-9)


def test_features_shape_and_names(small_settings):
    image, _ = make_blob(np.random.default_rng(1), size=(20, 24, 28))
    feats = compute_features(image, small_settings)
    names = feature_names(small_settings)
    assert feats.shape == (20, 24, 28, len(names)) and feats.dtype == np.float32
    assert len(set(names)) == len(names)
    assert np.isfinite(feats).all()


def test_features_invariant_to_rotation_of_the_grid(small_settings):
    """A 90-degree rotation of the voxel grid permutes the voxels, not the feature values."""
    image, _ = make_blob(np.random.default_rng(2), size=(26, 26, 26))
    arr = sitk.GetArrayFromImage(image)
    rotated = sitk.GetImageFromArray(np.ascontiguousarray(np.rot90(arr, k=1, axes=(0, 2))))
    f0 = compute_features(image, small_settings)
    f1 = compute_features(rotated, small_settings)
    np.testing.assert_allclose(np.rot90(f0, k=1, axes=(0, 2)), f1, rtol=1e-4, atol=1e-4)


def test_features_invariant_to_intensity_scaling(small_settings):
    image, _ = make_blob(np.random.default_rng(3), size=(20, 20, 20))
    scaled = image * 3.7 + 120.0
    np.testing.assert_allclose(
        compute_features(image, small_settings),
        compute_features(scaled, small_settings),
        rtol=1e-3,
        atol=1e-3,
    )


def test_features_use_mm_scales_on_anisotropic_images():
    """The same smooth scene sampled at 1 mm and at 2 mm along z gives the same features."""
    settings = FeatureSettings(
        scales_mm=(3.0,), kinds=("smoothed", "gradient"), normalisation="none"
    )

    def scene(spacing_z):
        n_z = int(round(40 / spacing_z))
        ref = sitk.Image([40, 40, n_z], sitk.sitkFloat32)
        ref.SetSpacing((1.0, 1.0, spacing_z))
        zyx = np.stack(
            np.meshgrid(*[np.arange(n_z), np.arange(40), np.arange(40)], indexing="ij"), -1
        ).reshape(-1, 3)
        pts = voxel_to_physical(ref, zyx)
        arr = np.exp(-np.sum((pts - [20.0, 20.0, 20.0]) ** 2, axis=1) / (2 * 6.0**2))
        image = sitk.GetImageFromArray(arr.reshape(n_z, 40, 40).astype(np.float32))
        image.CopyInformation(ref)
        return image

    iso, aniso = scene(1.0), scene(2.0)
    f_iso, f_aniso = compute_features(iso, settings), compute_features(aniso, settings)
    # Compare at physical points shared by both grids, away from the borders.
    for z_iso in (14, 20, 26):
        z_an = z_iso // 2
        a = f_iso[z_iso, 10:30, 10:30]
        b = f_aniso[z_an, 10:30, 10:30]
        np.testing.assert_allclose(b, a, rtol=0.05, atol=0.01 * np.abs(a).max())


def test_n4_option_gives_finite_features():
    image, _ = make_blob(np.random.default_rng(4), size=(24, 24, 24))
    settings = FeatureSettings(scales_mm=(2.0,), shell_radii_mm=(4.0,), n4=True)
    feats = compute_features(image, settings)
    assert np.isfinite(feats).all()


def test_feature_settings_json_roundtrip_and_validation():
    s = FeatureSettings(scales_mm=(1.5, 3.0), kinds=("smoothed", "hessian"), n4=True)
    again = FeatureSettings.from_dict(json.loads(json.dumps(s.to_dict())))
    assert again == s
    with pytest.raises(MedsegError, match="unknown feature kind"):
        FeatureSettings(kinds=("smoothed", "sift"))
    with pytest.raises(MedsegError, match="scales_mm"):
        FeatureSettings(scales_mm=(0.0,))
    with pytest.raises(MedsegError, match="newer medseg"):
        FeatureSettings.from_dict({**s.to_dict(), "colour": 1})


@pytest.mark.parametrize(
    "image",
    [
        sitk.Image([10, 10], sitk.sitkFloat32),
        sitk.Image([10, 10, 10], sitk.sitkVectorFloat32, 2),
        sitk.GetImageFromArray(np.full((8, 8, 8), np.nan, dtype=np.float32)),
    ],
    ids=["2d", "vector", "nan"],
)
def test_features_reject_bad_images(image):
    with pytest.raises(ImageGeometryError):
        compute_features(image)


# ----------------------------------------------------------------------------- sampling
def test_sampling_positives_within_radius_and_negatives_outside():
    rng = np.random.default_rng(5)
    image, lms = make_blob(rng, spacing=(1.5, 1.0, 0.8))
    lms[3] = np.nan  # a missing landmark
    shape = sitk.GetArrayViewFromImage(image).shape
    samples = sample_landmark_voxels(
        image,
        lms,
        positive_radius_mm=2.0,
        n_negative=90,
        max_positive=1000,
        random_state=np.random.RandomState(0),
    )
    for i, (pos, neg) in enumerate(zip(samples.positives, samples.negatives, strict=True)):
        if i == 3:
            assert pos.size == 0 and neg.size == 0
            continue
        p_mm = voxel_to_physical(image, np.stack(np.unravel_index(pos, shape), -1))
        n_mm = voxel_to_physical(image, np.stack(np.unravel_index(neg, shape), -1))
        assert np.all(np.linalg.norm(p_mm - lms[i], axis=1) <= 2.0 + 1e-9)
        assert np.all(np.linalg.norm(n_mm - lms[i], axis=1) > 2.0)
        assert pos.size >= 3 and neg.size == 90
        # a third of the negatives sit near the other landmarks (hard negatives)
        others = np.delete(lms, [i, 3], axis=0)
        near = np.linalg.norm(n_mm[:, None] - others[None], axis=-1).min(1) <= 8.0
        assert near.sum() >= 30


# ----------------------------------------------------------------------------- detector
def _recall_and_error(det, cases, **kwargs):
    hits, errors = [], []
    for image, lms in cases:
        cs = det.candidates(image, n_candidates=20, **kwargs)
        spacing = max(image.GetSpacing())
        hits.append(cs.recall(lms, radius_mm=2.0 * spacing))
        errors.append(cs.distances(lms)[:, 0])
    return float(np.mean(hits)), float(np.median(errors))


def test_detector_finds_landmarks_in_unseen_poses(fitted, blobs):
    recall, top1 = _recall_and_error(fitted, blobs[6:])
    assert recall >= 0.9
    assert top1 < 3.0  # mm; 1 mm voxels


def test_detector_works_on_oblique_anisotropic_image(fitted):
    """Trained on axis-aligned 1 mm images, tested on an oblique 1.3 x 1 x 0.9 mm grid."""
    direction = Rotation.from_euler("xyz", [20, -15, 35], degrees=True).as_matrix()
    rng = np.random.default_rng(11)
    cases = [make_blob(rng, size=(30, 36, 40), spacing=(0.9, 1.0, 1.3), direction=direction)]
    cases.append(make_blob(rng, size=(30, 36, 40), spacing=(0.9, 1.0, 1.3), direction=direction))
    hits = []
    for image, lms in cases:
        cs = fitted.candidates(image, n_candidates=20)
        hits.append(cs.recall(lms, radius_mm=2.6))
        np.testing.assert_allclose(
            physical_to_voxel(image, cs.positions.reshape(-1, 3)),
            cs.voxels.reshape(-1, 3),
            atol=1e-9,
        )
    assert np.mean(hits) >= 0.85


def test_multiclass_mode(blobs, small_settings):
    det = LandmarkDetector(
        features=small_settings,
        mode="multiclass",
        n_estimators=12,
        n_negative=150,
        n_mining_pool=4000,
        random_state=0,
        n_jobs=2,
    ).fit([b[0] for b in blobs[:6]], [b[1] for b in blobs[:6]])
    assert len(det.forests_) == 1
    assert det.stage1_ is None and det.n_features_ == small_settings.n_features
    recall, _ = _recall_and_error(det, blobs[6:])
    assert recall >= 0.85


def test_context_shells_peak_at_the_distance_of_the_other_landmarks():
    # stage-1 probability 1 at one coarse voxel: the shell means at a voxel 12 mm away are
    # largest for the radius nearest 12 mm, and zero for radii far from it
    coarse = np.zeros((1, 20, 20, 20), dtype=np.float32)
    coarse[0, 10, 10, 10] = 1.0
    radii = (4.0, 8.0, 12.0, 18.0)
    ctx = context_features(
        coarse,
        spacing_zyx=np.ones(3),
        stride=2,
        shape=(40, 40, 40),
        groups=np.zeros(1, dtype=int),
        radii_mm=radii,
    )
    assert ctx.shape == (40, 40, 40, 4)
    at_12mm = ctx[20, 20, 32]  # full voxel (20, 20, 20) is the peak; 12 voxels of 1 mm away
    assert np.argmax(at_12mm) == 2
    assert at_12mm[0] < 1e-6 * at_12mm[2]
    # rotation invariance: the same distance along another axis gives the same features
    np.testing.assert_allclose(ctx[20, 8, 20], at_12mm, rtol=1e-5, atol=1e-6 * at_12mm.max())


def test_auto_context_detector_has_two_stages(fitted, small_settings):
    assert fitted.auto_context and fitted.stage1_ is not None
    assert fitted.stage1_.stage1_ is None  # stage 1 is a plain one-stage detector
    n_groups = int(fitted.context_groups_.max()) + 1
    assert fitted.n_features_ == small_settings.n_features + n_groups * len(
        fitted.context_radii_mm_
    )
    assert fitted.feature_names_[-1].startswith("context_g")
    # radii span the distances between the landmarks of the training blobs (mm)
    assert 1.0 < min(fitted.context_radii_mm_) < max(fitted.context_radii_mm_) < 40.0


def test_scale_augmentation_and_mining_add_samples(blobs, small_settings):
    images, lms = [b[0] for b in blobs[:2]], [b[1] for b in blobs[:2]]
    kwargs = dict(
        features=small_settings,
        n_estimators=3,
        n_negative=60,
        max_positive=10**6,
        n_mining_pool=2000,
    )
    plain = LandmarkDetector(n_mining_rounds=0, random_state=0, **kwargs).fit(images, lms)
    aug = LandmarkDetector(
        n_mining_rounds=1, augment_scales=(0.5,), forest="extra_trees", random_state=0, **kwargs
    ).fit(images, lms)
    # a copy at half the size: the 2 mm ball holds 8x the voxels (1 mm spacing -> 0.5 mm)
    assert np.all(aug.n_samples_[:, 1] > 4 * plain.n_samples_[:, 1])
    # one mining round adds n_negative // 2 hard negatives per image (and per scaled copy)
    assert np.all(aug.n_samples_[:, 0] == 2 * plain.n_samples_[:, 0] + 4 * 30)


def test_trees_grow_on_at_most_max_tree_samples_rows(blobs, small_settings):
    images, lms = [b[0] for b in blobs[:2]], [b[1] for b in blobs[:2]]
    kwargs = dict(features=small_settings, n_estimators=3, n_negative=60, n_mining_pool=2000)
    capped = LandmarkDetector(max_tree_samples=40, random_state=0, **kwargs).fit(images, lms)
    full = LandmarkDetector(max_tree_samples=None, random_state=0, **kwargs).fit(images, lms)
    n_rows = capped.n_samples_.sum(axis=1)
    assert np.all(n_rows > 100)  # so the cap binds
    for forest in capped.forests_:
        # a bootstrap of 40 draws holds at most 40 distinct rows
        assert all(tree.tree_.n_node_samples[0] <= 40 for tree in forest.estimators_)
    assert all(t.tree_.n_node_samples[0] <= 40 for t in capped.region_forest_.estimators_)
    for forest in full.forests_:
        assert all(tree.tree_.n_node_samples[0] > 40 for tree in forest.estimators_)
    with pytest.raises(ParameterError, match="max_tree_samples"):
        LandmarkDetector(max_tree_samples=0, **kwargs).fit(images, lms)


def test_same_seed_same_candidates_whatever_the_jobs(blobs, small_settings):
    """The training copies (scaled and posed) run on threads, each with its own seed: the
    model depends on ``random_state``, not on ``n_jobs`` or the order copies finish in."""
    kwargs = dict(
        features=small_settings,
        n_estimators=4,
        n_negative=60,
        n_mining_pool=2000,
        augment_poses=1,
    )
    train = ([b[0] for b in blobs[:3]], [b[1] for b in blobs[:3]])

    def candidates(seed, jobs):
        detector = LandmarkDetector(**kwargs, random_state=seed, n_jobs=jobs).fit(*train)
        return detector.candidates(blobs[8][0], n_candidates=5)

    a, b, other = candidates(3, 1), candidates(3, 2), candidates(4, 2)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.probabilities, b.probabilities)
    assert not np.array_equal(a.probabilities, other.probabilities)
    # set to one job (as medseg-segment's workers do), no forest uses the fitting's pool
    two = LandmarkDetector(**kwargs, random_state=3, n_jobs=2).fit(*train)
    two.n_jobs = 1
    assert two.region_forest_ is not None
    for forest in [*two.forests_, two.region_forest_]:
        forest.predict_proba = None
    np.testing.assert_array_equal(
        two.candidates(blobs[8][0], n_candidates=5).probabilities, a.probabilities
    )


def test_candidates_structure_and_min_distance(fitted, blobs):
    image, _ = blobs[7]
    cs = fitted.candidates(image, n_candidates=15, min_distance_mm=4.0, stride=1, refine=False)
    assert cs.positions.shape == (7, 15, 3) and cs.probabilities.shape == (7, 15)
    assert np.all(np.diff(cs.probabilities, axis=1) <= 0)  # best first
    for i in range(7):
        d = np.linalg.norm(cs.positions[i][:, None] - cs.positions[i][None], axis=-1)
        assert d[np.triu_indices(15, 1)].min() > 4.0
    u = cs.unaries()
    np.testing.assert_allclose(u, -np.log(cs.probabilities))
    assert np.isfinite(u).all() and (u >= 0).all()


def test_the_screen_scores_exactly_the_rows_the_first_trees_rate_best(fitted, blobs):
    """A screened forest gives the rows its first trees rate best the probabilities of all
    its trees, to the bit, and the others the mean of those first trees, capped so that
    they rank after them."""
    from medseg.detection._prediction import forest_features, forest_proba, screened_proba

    image = blobs[7][0]
    rows = forest_features(fitted, image, None).reshape(-1, fitted.n_features_)[::3]
    rows = rows.astype(np.float32)
    forest = fitted.forests_[0]
    pos = list(forest.classes_).index(1)
    got = screened_proba(forest, rows, 3, 50)
    every = forest_proba(forest, rows)[:, pos]
    first = np.mean([tree.predict_proba(rows)[:, pos] for tree in forest.estimators_[:3]], 0)
    exact = got == every
    assert exact.sum() >= 50  # the 50 screened, and others where the two agree
    chosen = np.argsort(-first, kind="stable")[:50]
    assert exact[chosen].all()
    cap = got[chosen].min()
    left_out = np.delete(got, chosen)
    assert left_out.max() < cap  # ranked after every row screened in
    np.testing.assert_allclose(left_out, np.minimum(np.delete(first, chosen), cap), atol=1e-12)
    assert (np.delete(first, chosen) > cap).any()  # the cap is needed on this image
    assert not np.array_equal(got, every)  # the first trees alone do not rate every row alike


def test_a_screen_as_wide_as_the_image_changes_no_candidate(fitted, blobs):
    image = blobs[6][0]
    every = fitted.candidates(image, n_candidates=5, screen=None)
    wide = fitted.candidates(image, n_candidates=5, screen=(3, 10**6))
    assert np.array_equal(every.positions, wide.positions)
    assert np.array_equal(every.probabilities, wide.probabilities)
    with pytest.raises(ParameterError, match="screen"):
        fitted.candidates(image, n_candidates=5, screen=(3, 4))
    with pytest.raises(ParameterError, match="screen"):
        fitted.candidates(image, n_candidates=5, screen=(0, 400))


def test_a_narrow_screen_keeps_exact_scores_best_first_and_apart(fitted, blobs):
    """Screened to 40 voxels a landmark, the candidates still come best first and apart,
    and the best carries its exact probability; the screen changed some of them."""
    image = blobs[6][0]
    kwargs = dict(n_candidates=6, min_distance_mm=4.0, stride=1, refine=False)
    every = fitted.candidates(image, screen=None, **kwargs)
    screened = fitted.candidates(image, screen=(3, 40), **kwargs)
    maps = fitted.predict_proba_map(image, stride=1)
    for i in range(7):
        z, y, x = np.rint(screened.voxels[i, 0]).astype(int)
        assert screened.probabilities[i, 0] == pytest.approx(maps[i, z, y, x], abs=1e-6)
        d = np.linalg.norm(screened.positions[i][:, None] - screened.positions[i][None], axis=-1)
        assert d[np.triu_indices(6, 1)].min() > 4.0
    assert np.all(np.diff(screened.probabilities, axis=1) <= 0)
    assert not np.array_equal(screened.positions, every.positions)


def test_probability_map_agrees_with_candidates(fitted, blobs):
    image, _ = blobs[6]
    maps = fitted.predict_proba_map(image, stride=1)
    assert maps.shape == (7,) + sitk.GetArrayViewFromImage(image).shape
    assert np.nanmin(maps) >= 0 and np.nanmax(maps) <= 1
    cs = fitted.candidates(image, n_candidates=3, stride=1, refine=False)
    for i in range(7):
        assert cs.probabilities[i, 0] == pytest.approx(np.nanmax(maps[i]), abs=1e-6)
    strided = fitted.predict_proba_map(image, stride=3)
    assert np.isnan(strided[:, 1, :, :]).all() and np.isfinite(strided[:, ::3, ::3, ::3]).all()


def test_mask_restricts_the_search(fitted, blobs):
    image, lms = blobs[6]
    shape = sitk.GetArrayViewFromImage(image).shape
    mask = np.zeros(shape, dtype=bool)
    mask[:, :, : shape[2] // 2] = True
    cs = fitted.candidates(image, n_candidates=10, mask=mask)
    assert np.all(np.rint(cs.voxels[..., 2]) < shape[2] // 2)
    mask_image = sitk.GetImageFromArray(mask.astype(np.uint8))
    mask_image.CopyInformation(image)
    cs2 = fitted.candidates(image, n_candidates=10, mask=mask_image)
    np.testing.assert_array_equal(cs.positions, cs2.positions)


def test_constant_image_gives_low_confidence_candidates(fitted):
    image = sitk.Image([30, 30, 30], sitk.sitkFloat32) + 5.0
    cs = fitted.candidates(image, n_candidates=20)
    assert cs.positions.shape == (7, 20, 3)
    assert np.isfinite(cs.unaries()).all()
    # distinct positions, and no landmark is confidently found
    for i in range(7):
        assert len(np.unique(np.round(cs.positions[i], 3), axis=0)) == 20
    assert cs.probabilities.max() < 0.5


def test_bad_input_errors(fitted, blobs, small_settings):
    with pytest.raises(NotFittedError, match="not fitted"):
        LandmarkDetector().candidates(blobs[0][0])
    with pytest.raises(ImageGeometryError, match="trained on 3D"):
        fitted.candidates(sitk.Image([20, 20], sitk.sitkFloat32))
    with pytest.raises(LabelError, match="empty"):
        fitted.candidates(blobs[0][0], mask=np.zeros((36, 36, 36), bool))
    with pytest.raises(ImageGeometryError, match="shape"):
        fitted.candidates(blobs[0][0], mask=np.ones((10, 36, 36), bool))
    with pytest.raises(ParameterError, match="mode"):
        LandmarkDetector(mode="joint").fit([blobs[0][0]], [blobs[0][1]])
    with pytest.raises(ParameterError, match="n_estimators"):
        LandmarkDetector(n_estimators=0).fit([blobs[0][0]], [blobs[0][1]])
    with pytest.raises(ParameterError, match="stride"):
        fitted.candidates(blobs[0][0], stride=0)
    # no pool to mine from: refused before any work, not an AttributeError after it
    with pytest.raises(ParameterError, match="n_mining_pool"):
        LandmarkDetector(n_mining_pool=0).fit([blobs[0][0]], [blobs[0][1]])
    with pytest.raises(MedsegError, match="landmarks"):
        LandmarkDetector(features=small_settings).fit(
            [blobs[0][0], blobs[1][0]], [blobs[0][1], blobs[1][1][:3]]
        )


def test_detector_is_a_scikit_learn_estimator(fitted, small_settings):
    assert isinstance(fitted, BaseEstimator)
    copy = clone(fitted)
    assert not hasattr(copy, "forests_") and not hasattr(copy, "n_landmarks_")
    assert copy.get_params() == fitted.get_params()
    assert copy.features == small_settings and copy.auto_context
    with pytest.raises(ValueError, match="colour"):
        copy.set_params(colour="red")
    assert copy.set_params(n_estimators=5).n_estimators == 5 and fitted.n_estimators == 12
    assert repr(LandmarkDetector(mode="multiclass")) == "LandmarkDetector(mode='multiclass')"
    # __init__ only stores: a bad value is refused by fit, as a ValueError too
    bad = LandmarkDetector(min_samples_leaf=0)
    assert bad.min_samples_leaf == 0
    with pytest.raises(ValueError, match="min_samples_leaf"):
        bad.fit([], [])


def test_feature_maps_above_the_memory_limit_are_refused(fitted, blobs, monkeypatch):
    monkeypatch.setenv("MEDSEG_MEMORY_LIMIT_GB", "0.001")  # 1 MiB
    with pytest.raises(ResourceLimitError, match="feature maps of a .* image"):
        fitted.candidates(blobs[7][0])
    with pytest.raises(ResourceLimitError, match="crop the image"):
        LandmarkDetector(n_estimators=2).fit([blobs[0][0]], [blobs[0][1]])


def test_candidate_set_recall_counts_hits():
    cs = CandidateSet(
        positions=np.array([[[0, 0, 0], [5, 0, 0]], [[0, 0, 0], [0, 9, 0]]], float),
        probabilities=np.array([[0.9, 0.1], [0.0, 0.5]]),
        voxels=np.zeros((2, 2, 3)),
        floor=1e-3,
    )
    ref = np.array([[5.5, 0, 0], [0, 0, 3.0]])
    np.testing.assert_array_equal(cs.recall(ref, radius_mm=1.0), [1.0, 0.0])
    np.testing.assert_array_equal(cs.recall(ref, radius_mm=1.0, n=1), [0.0, 0.0])
    assert cs.unaries()[1, 0] == pytest.approx(-np.log(1e-3))


def test_non_maximum_suppression_on_a_flat_map_fills_all_slots():
    grid = np.stack(np.meshgrid(*[np.arange(6)] * 3, indexing="ij"), -1).reshape(-1, 3)
    keep = non_maximum_suppression(
        np.zeros(len(grid)),
        grid.astype(float),
        n=10,
        min_distance_mm=2.5,
        grid_shape=(6, 6, 6),
        footprint_vox=[2.5] * 3,
    )
    assert len(keep) == 10 and len(np.unique(keep)) == 10
    d = np.linalg.norm(grid[keep][:, None] - grid[keep][None], axis=-1)
    assert d[np.triu_indices(10, 1)].min() > 2.5


# ----------------------------------------------------------------------------- persistence
def test_save_load_roundtrip(fitted, blobs, tmp_path):
    path = tmp_path / "det"
    fitted.save(path)
    loaded = LandmarkDetector.load(path)
    assert loaded.features == fitted.features and loaded.mode == fitted.mode
    # the parameters come back as they went in (tuples stay tuples through JSON)
    assert loaded.get_params() == fitted.get_params()
    # every constructor parameter is written, the feature settings as a plain dictionary
    params = json.loads((path / "detector.json").read_text())["params"]
    assert set(params) == set(fitted.get_params())
    assert params["features"] == fitted.features.to_dict()
    a = fitted.candidates(blobs[7][0], n_candidates=5)
    b = loaded.candidates(blobs[7][0], n_candidates=5)
    np.testing.assert_array_equal(a.positions, b.positions)
    fitted.save(path)  # replacing a saved detector is allowed
    assert sorted(p.name for p in tmp_path.iterdir()) == ["det"]


def test_load_rejects_bad_files(fitted, tmp_path):
    with pytest.raises(InputFileError, match="not a saved detector"):
        LandmarkDetector.load(tmp_path)
    (tmp_path / "notes.txt").write_text("keep me")
    with pytest.raises(InputFileError, match="overwritten"):
        fitted.save(tmp_path / "notes.txt")
    path = tmp_path / "det"
    fitted.save(path)
    meta = json.loads((path / "detector.json").read_text())
    meta["version"] = 99
    (path / "detector.json").write_text(json.dumps(meta))
    with pytest.raises(ModelFileError, match="newer"):
        LandmarkDetector.load(path)
    fitted.save(path)
    (path / "forests.npz").write_bytes(b"not a zip file")
    with pytest.raises(ModelFileError, match="corrupt"):
        LandmarkDetector.load(path)
    fitted.save(path)
    shutil.rmtree(path / "stage1")
    with pytest.raises(ModelFileError, match="stage1"):
        LandmarkDetector.load(path)


# ----------------------------------------------------------------------------- real data
@pytest.mark.data
def test_features_on_real_hippocampus_image(hippocampus_dir):
    image = sitk.ReadImage(str(hippocampus_dir / "imagesTr" / "hippocampus_001.nii.gz"))
    feats = compute_features(image)
    assert feats.shape[:3] == sitk.GetArrayViewFromImage(image).shape
    assert np.isfinite(feats).all()
    # normalised intensity: the 1st / 99th percentiles map to about 0 and 1
    lo, hi = np.percentile(feats[..., 0], [1, 99])
    assert lo == pytest.approx(0.0, abs=0.02) and hi == pytest.approx(1.0, abs=0.02)


def test_posed_copy_moves_the_landmarks_with_the_image(blobs):
    """A posed training copy: the image resampled and its landmarks mapped by one transform,
    so each landmark still sits on the same anatomy (the same interpolated intensity)."""
    from medseg.detection._training import _posed

    image, landmarks = blobs[0]
    detector = LandmarkDetector(augment_angle_deg=120.0, augment_scale_range=(0.7, 1.4))
    rng = np.random.RandomState(3)

    def values(img, points):  # linear interpolation at physical points
        voxels = physical_to_voxel(img, points)  # (z, y, x), as the arrays
        return ndimage.map_coordinates(sitk.GetArrayFromImage(img), voxels.T, order=1)

    for _ in range(4):
        moved, moved_landmarks = _posed(image, landmarks, detector, rng)
        assert moved.GetSize() > image.GetSize()  # the padded field of view
        a, b = values(image, landmarks), values(moved, moved_landmarks)
        spread = float(np.ptp(sitk.GetArrayViewFromImage(image)))
        assert np.median(np.abs(np.subtract(a, b))) < 0.05 * spread
        # a similarity: the landmarks' shape is kept up to scale
        d0 = np.linalg.norm(landmarks[:, None] - landmarks[None], axis=-1)
        d1 = np.linalg.norm(moved_landmarks[:, None] - moved_landmarks[None], axis=-1)
        ratio = d1[d0 > 0] / d0[d0 > 0]
        assert np.ptp(ratio) < 1e-9 and 0.7 - 1e-9 <= ratio[0] <= 1.4 + 1e-9


def test_posed_copies_add_training_samples(blobs, small_settings):
    kwargs = dict(features=small_settings, n_estimators=2, random_state=0)
    images, landmarks = [b[0] for b in blobs[:2]], [b[1] for b in blobs[:2]]
    plain = LandmarkDetector(**kwargs).fit(images, landmarks)
    posed = LandmarkDetector(**kwargs, augment_poses=2).fit(images, landmarks)
    # positives: every copy contributes its landmark neighbourhoods (three times as many,
    # up to the voxels the resampling puts within the radius)
    ratio = posed.n_samples_[:, 1].sum() / plain.n_samples_[:, 1].sum()
    assert 2.0 <= ratio <= 4.0


def test_forests_score_as_scikit_learn_does_on_one_job_whatever_the_threads(fitted, blobs):
    """``forest_proba`` sums the trees in the forest's order, as scikit-learn does on one
    job: the same probabilities to the bit, for float64 and float32 rows, and on two threads
    (the rows split in two blocks) as on one."""
    from medseg.detection._prediction import _ROWS_PER_THREAD, forest_features, forest_proba

    image = blobs[7][0]
    rows = forest_features(fitted, image, None).reshape(-1, fitted.n_features_)[::7]
    assert len(rows) >= 2 * _ROWS_PER_THREAD  # enough for two threads' blocks
    for forest in fitted.forests_[:3]:
        saved = forest.n_jobs
        try:
            forest.n_jobs = 1
            expected = forest.predict_proba(rows)
            for jobs in (1, 2):
                forest.n_jobs = jobs
                for X in (rows.astype(np.float64), rows.astype(np.float32)):
                    got = forest_proba(forest, X)
                    assert got.dtype == np.float64 and np.array_equal(got, expected)
            assert 0.0 < expected[:, 1].max() and expected[:, 1].min() < 1.0  # not constant
        finally:
            forest.n_jobs = saved
    with pytest.raises(ValueError, match="features"):  # checked once, not per tree
        forest_proba(fitted.forests_[0], rows[:, :-1])
