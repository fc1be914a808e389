"""The appearance check in the shape's frame: a turned copy of the shape is seen and undone."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from medseg.errors import ModelFileError, ParameterError
from medseg.frame import ShapeFrame
from medseg.io import padded_grid, resample_affine
from medseg.segmenter import FrameAppearance
from medseg.segmenter._appearance import icosahedral_rotations, search_turns

SIZE = 44  # voxels of 1 mm
AXES = np.array([11.0, 6.0, 5.0])  # the ellipsoid's semi-axes, mm


def _sites(n: int = 24) -> np.ndarray:
    """Points on the ellipsoid's surface (its own frame, centred at 0)."""
    m = np.arange(n) + 0.5
    z = 1 - 2 * m / n
    phi = np.pi * (1 + 5**0.5) * m
    u = np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], 1)
    return u * AXES


def _render(rotation: np.ndarray, rng) -> tuple[sitk.Image, np.ndarray]:
    """An ellipsoid (symmetric under half-turns about its axes) with a blob beside its
    head on one side, the only thing that tells a half-turned copy from the right one;
    posed by ``rotation`` about the image centre. Returns the image and the landmarks."""
    centre = np.full(3, (SIZE - 1) / 2.0)
    grid = np.stack(np.meshgrid(*[np.arange(SIZE)] * 3, indexing="ij"), -1)  # (x, y, z)
    local = (grid - centre) @ rotation  # into the shape's own frame
    inside = ((local / AXES) ** 2).sum(-1) <= 1
    blob = np.linalg.norm(local - np.array([7.0, 9.0, 0.0]), axis=-1) <= 4.0
    values = 40.0 + 60.0 * inside + 35.0 * blob + rng.normal(0, 4.0, inside.shape)
    image = sitk.GetImageFromArray(values.transpose(2, 1, 0).astype(np.float32))
    return image, _sites() @ rotation.T + centre


def _lands_on(frame: ShapeFrame, transform, points: np.ndarray) -> bool:
    """Whether ``transform`` carries the frame's reference shape within 4 mm (mean) of
    ``points``: the other starts of the search lie 6 mm or more off."""
    placed = np.array([transform.TransformPoint(p) for p in frame.reference.tolist()])
    return bool(np.linalg.norm(placed - points, axis=1).mean() < 4.0)


@pytest.fixture(scope="module")
def trained():
    rng = np.random.default_rng(0)
    poses = Rotation.random(6, random_state=1).as_matrix()
    cases = [_render(rotation, rng) for rotation in poses]
    images, shapes = [c[0] for c in cases], np.stack([c[1] for c in cases])
    frame = ShapeFrame.fit(shapes, images)
    return frame, FrameAppearance().fit(frame, images, shapes)


def test_the_starts_are_60_proper_rotations_identity_first_none_farther_than_45_degrees():
    group = icosahedral_rotations()
    assert group.shape == (60, 3, 3)
    np.testing.assert_allclose(group[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(group), 1.0)
    assert len({tuple(np.round(r, 6).ravel()) for r in group}) == 60
    starts = Rotation.from_matrix(group)
    anywhere = Rotation.random(2000, random_state=0)
    nearest = np.min([(anywhere * start.inv()).magnitude() for start in starts], axis=0)
    assert np.degrees(nearest.max()) < 45.0


def test_the_half_turns_about_the_shapes_own_axes_are_among_the_starts(trained):
    """An elongated shape turned about one of its principal axes lies on its own surface:
    the turned copy the check is for. The starts undo each such turn exactly."""
    frame, _ = trained
    turns = search_turns(frame)
    assert turns.shape == (60, 3, 3)
    np.testing.assert_allclose(turns[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(turns), 1.0)
    centred = frame.reference - frame.reference.mean(axis=0)
    axes = np.linalg.svd(centred, full_matrices=False)[2]  # rows, largest spread first
    for axis in axes:
        half = Rotation.from_rotvec(np.pi * axis).as_matrix()
        assert np.min(np.linalg.norm(turns - half, axis=(1, 2))) < 1e-9


def test_a_half_turned_shape_scores_low_and_the_search_puts_it_right(trained):
    frame, check = trained
    rotation = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix()  # a pose never trained
    image, truth = _render(rotation, np.random.default_rng(5))
    centre = truth.mean(axis=0)
    long_axis = rotation[:, 0]  # the half-turn about it maps the ellipsoid onto itself
    half = Rotation.from_rotvec(np.pi * long_axis).as_matrix()
    turned = (truth - centre) @ half.T + centre  # on the same surface, each site elsewhere
    assert np.linalg.norm(turned - truth, axis=1).mean() > 8.0

    right, wrong = check.score(frame, image, truth), check.score(frame, image, turned)
    assert right >= check.threshold_ - 0.05 and wrong < check.threshold_
    assert wrong < right - 0.02
    found = check.search(frame, image, turned)[0]
    assert found.shape == truth.shape
    assert np.linalg.norm(found - truth, axis=1).mean() < 2.0


def test_the_screens_coarse_copy_lies_where_the_image_lies():
    """The screen registers a cropped, smoothed, coarse copy of the image: on an oblique,
    anisotropic grid, a linear ramp (which a Gaussian leaves as it is) keeps its value at
    every physical point of the copy away from the edges, and the crop holds the ball."""
    import medseg.segmenter._appearance as appearance

    size, spacing, origin = (40, 36, 30), np.array([0.8, 1.0, 1.5]), np.array([5.0, -12.0, 30.0])
    direction = Rotation.from_rotvec([0.4, -0.3, 0.7]).as_matrix()
    slope = np.array([0.5, -1.0, 2.0])  # the ramp's value per mm
    index = np.stack(np.meshgrid(*[np.arange(n) for n in size], indexing="ij"), -1)
    points = origin + (index * spacing) @ direction.T
    image = sitk.GetImageFromArray((points @ slope).transpose(2, 1, 0).astype(np.float32))
    image.SetSpacing(spacing.tolist())
    image.SetDirection(direction.ravel().tolist())
    image.SetOrigin(origin.tolist())

    centre = image.TransformContinuousIndexToPhysicalPoint((20.0, 18.0, 15.0))
    cropped = appearance._cropped(image, np.asarray(centre), 10.0)
    assert cropped.GetSize() < image.GetSize()
    for sign in (-1.0, 1.0):
        for axis in direction.T:
            inside = cropped.TransformPhysicalPointToContinuousIndex(
                (np.asarray(centre) + sign * 10.0 * axis).tolist()
            )
            assert all(-0.5 <= i <= n - 0.5 for i, n in zip(inside, cropped.GetSize(), strict=True))
    coarse, mask = appearance._coarse(cropped, None, 2.0)
    assert mask is None and coarse.GetSpacing() == pytest.approx((2.0, 2.0, 2.0))
    assert coarse.GetDirection() == pytest.approx(image.GetDirection())
    values = sitk.GetArrayFromImage(coarse).transpose(2, 1, 0)  # (x, y, z)
    for index in np.ndindex(*(n - 4 for n in values.shape)):  # 2 voxels from every edge
        index = tuple(int(i) + 2 for i in index)
        point = coarse.TransformIndexToPhysicalPoint(index)
        assert values[index] == pytest.approx(float(np.dot(point, slope)), abs=0.05)


def test_the_screens_coarse_copy_keeps_a_padding_out_of_the_content():
    """Smoothed over the content alone, an image of 100 (and noise) padded with zeros stays
    100 at every voxel the coarse mask keeps (smoothed plainly, the zeros would pull its edge
    down), and the copy is float32, as the fixed mean is: a registration of two types fails,
    and the screen would then keep every start where it is."""
    import medseg.segmenter._appearance as appearance

    values = np.zeros((30, 30, 30), dtype=np.float32)
    values[6:24, 6:24, 6:24] = np.random.default_rng(0).normal(100.0, 1.0, (18, 18, 18))
    image = sitk.GetImageFromArray(values)
    image.SetSpacing((1.0, 1.0, 1.0))
    mask = appearance._padding_excluded(image)
    assert mask is not None
    coarse, kept = appearance._coarse(sitk.Cast(image, sitk.sitkFloat64), mask, 2.0)
    assert coarse.GetPixelID() == sitk.sitkFloat32 and kept is not None
    inside = sitk.GetArrayFromImage(kept) > 0
    assert inside.sum() >= 6**3
    np.testing.assert_allclose(sitk.GetArrayFromImage(coarse)[inside], 100.0, atol=0.5)


def test_a_turned_copy_is_replaced_a_small_correction_is_not(trained):
    """The searched landmarks replace the found ones when they correlate better and the
    found ones are the shape turned about itself; a found shape tilted a little from the
    truth stays, though the truth correlates better: a local correction is the detectors'
    and the profile search's to judge."""
    frame, check = trained
    rotation = Rotation.from_rotvec([-0.9, 0.4, 1.1]).as_matrix()
    image, truth = _render(rotation, np.random.default_rng(7))
    centre = truth.mean(axis=0)
    half = Rotation.from_rotvec(np.pi * rotation[:, 0]).as_matrix()
    turned = (truth - centre) @ half.T + centre
    tilt = Rotation.from_rotvec(np.deg2rad(15.0) * rotation[:, 2]).as_matrix()
    tilted = (truth - centre) @ tilt.T + centre

    better, seen = check.prefers(frame, image, turned, truth)
    assert better and seen["turn_deg"] == pytest.approx(180.0, abs=1e-3)
    assert not check.prefers(frame, image, truth, turned)[0]  # the right one stays
    better, seen = check.prefers(frame, image, tilted, truth)
    near, box = check.scores(frame, image, tilted)
    assert seen["search_score"] > near and seen["search_box_score"] > box
    assert seen["turn_deg"] == pytest.approx(15.0, abs=1e-3) and not better


def test_save_load_round_trip_and_refusals(trained, tmp_path):
    frame, check = trained
    loaded = FrameAppearance.load(check.save(tmp_path / "appearance.npz"))
    np.testing.assert_array_equal(loaded.mean_, check.mean_)
    assert loaded.threshold_ == check.threshold_ and loaded.fits(frame)
    image, truth = _render(np.eye(3), np.random.default_rng(2))
    assert loaded.score(frame, image, truth) == check.score(frame, image, truth)
    other = ShapeFrame(frame.reference, frame.lower, frame.upper + 6.0, frame.spacing)
    assert not loaded.fits(other)
    with pytest.raises(ParameterError, match="another frame"):
        loaded.score(other, image, truth)
    (tmp_path / "bad.npz").write_bytes(b"not an archive")
    with pytest.raises(ModelFileError):
        FrameAppearance.load(tmp_path / "bad.npz")
    with pytest.raises(ParameterError, match="at least 2"):
        FrameAppearance().fit(frame, [image], truth[None])


def test_a_field_of_view_padded_with_zeros_is_seen_as_the_image_alone(trained):
    """Padded by 12 mm of zeros, the image scores and registers as it does unpadded (a
    constant padding is no content: :func:`medseg.io.content_mask`). Counted, the zeros
    took the truth's box score from about 0.95 to 0.36 and the search 3 mm off."""
    frame, check = trained
    rotation = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix()
    image, truth = _render(rotation, np.random.default_rng(5))
    centre = truth.mean(axis=0)
    half = Rotation.from_rotvec(np.pi * rotation[:, 0]).as_matrix()
    turned = (truth - centre) @ half.T + centre
    padded = resample_affine(image, np.eye(3), np.zeros(3), padded_grid(image, 12.0), fill="zeros")
    for landmarks in (truth, turned):
        np.testing.assert_allclose(
            check.scores(frame, padded, landmarks), check.scores(frame, image, landmarks),
            atol=0.02,
        )  # fmt: skip
    found = check.search(frame, padded, turned)[0]
    assert np.linalg.norm(found - truth, axis=1).mean() < 2.0
    assert check.prefers(frame, padded, turned, found)[0]


def test_of_the_converged_registrations_the_one_that_fits_near_the_shape_wins(trained, monkeypatch):
    """The registrations maximise the correlation over the frame's box, which a placement
    turned from the truth can win by a hair (phantom: 0.613 against 0.607); the search then
    returns the converged registration that correlates best near the structure. Here the
    registration is a fake: the start nearest the truth (0.1 mm off; the other 59 are 6 mm
    or more) is rated first in the screen and converges onto the truth, rated last; the
    others stay where they start (the half-turned copy among them, 0.95 near the shape
    against the truth's 0.98, and rated above it over the box)."""
    import medseg.segmenter._appearance as appearance

    frame, check = trained
    rotation = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix()
    image, truth = _render(rotation, np.random.default_rng(5))
    centre = truth.mean(axis=0)
    turned = (truth - centre) @ Rotation.from_rotvec(np.pi * rotation[:, 0]).as_matrix().T
    turned += centre
    onto_truth = appearance._frame_to_image(
        frame.pose(truth), np.eye(3), frame.reference.mean(axis=0)
    )

    def fake_register(fixed, moving, mask, start, iterations, **options):
        at_truth = _lands_on(frame, start, truth)
        if iterations != appearance._FINAL_ITERATIONS:  # the screen
            return (1.0 if at_truth else 0.9), sitk.Similarity3DTransform(start)
        if at_truth:
            return 0.5, sitk.Similarity3DTransform(onto_truth)
        return 0.9, sitk.Similarity3DTransform(start)

    monkeypatch.setattr(appearance, "_register", fake_register)
    placed = check.search(frame, image, turned)
    assert placed.shape == (appearance._KEPT_STARTS, *truth.shape)
    assert np.linalg.norm(placed[0] - truth, axis=1).mean() < 0.01


def test_the_found_frame_is_refined_even_when_the_screen_ranks_it_last(trained, monkeypatch):
    """The screen's coarse correlation can rank the found frame below turned ones (phantom
    turned by 30 degrees: 10th of 60, none of the six kept within 100 degrees of it), and a
    turned shape would then only have to beat the found landmarks as they are. Here the fake
    screen rates the found frame (right: the truth) last and every turned start alike; the
    refined placements must still hold it, beside the six best."""
    import medseg.segmenter._appearance as appearance

    frame, check = trained
    rotation = Rotation.from_rotvec([-0.7, 0.4, 1.1]).as_matrix()
    image, truth = _render(rotation, np.random.default_rng(7))

    def fake_register(fixed, moving, mask, start, iterations, **options):
        screen = iterations != appearance._FINAL_ITERATIONS
        score = (0.0 if _lands_on(frame, start, truth) else 1.0) if screen else 0.5
        return score, sitk.Similarity3DTransform(start)

    monkeypatch.setattr(appearance, "_register", fake_register)
    placed = check.search(frame, image, truth)
    assert placed.shape == (appearance._KEPT_STARTS + 1, *truth.shape)
    off = np.linalg.norm(placed - truth, axis=2).mean(axis=1)
    assert np.sum(off < 4.0) == 1
