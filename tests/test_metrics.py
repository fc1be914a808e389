"""Metrics checked against hand-computed cases and a brute-force reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage
from scipy.spatial import cKDTree

from medseg.errors import ImageGeometryError
from medseg.evaluation.metrics import (
    assd,
    dice,
    dice_per_label,
    hd95,
    landmark_errors,
    score_segmentation,
)
from medseg.io import voxel_to_physical

SPACING = (0.5, 1.0, 2.0)  # x, y, z


def _image(array: np.ndarray, spacing=SPACING, direction=None) -> sitk.Image:
    image = sitk.GetImageFromArray(array.astype(np.uint8))
    image.SetSpacing(spacing)
    if direction is not None:
        image.SetDirection(direction)
    return image


def test_single_voxels_hand_computed():
    a = np.zeros((8, 8, 12), np.uint8)
    b = np.zeros_like(a)
    a[4, 4, 2] = 1
    b[4, 4, 6] = 1  # 4 voxels apart along x at 0.5 mm
    assert dice(_image(a), _image(b)) == 0.0
    assert hd95(_image(a), _image(b)) == pytest.approx(2.0)
    assert assd(_image(a), _image(b)) == pytest.approx(2.0)


def test_half_overlap_dice_hand_computed():
    a = np.zeros((6, 6, 6), np.uint8)
    b = np.zeros_like(a)
    a[1:5, 1:5, 1:3] = 1  # 32 voxels
    b[1:5, 1:5, 2:4] = 1  # 32 voxels, 16 shared
    assert dice(_image(a), _image(b)) == pytest.approx(0.5)


def test_identical_masks_have_zero_distance():
    a = np.zeros((10, 10, 10), np.uint8)
    a[2:8, 3:7, 2:9] = 1
    scores = score_segmentation(_image(a), _image(a))
    assert scores.dice == 1.0 and scores.hd95 == 0.0 and scores.assd == 0.0


def _border(mask: np.ndarray) -> np.ndarray:
    return mask & ~ndimage.binary_erosion(mask, structure=np.ones((3, 3, 3)), border_value=0)


def test_surface_distances_match_brute_force_on_oblique_anisotropic_blobs():
    rng = np.random.default_rng(3)
    masks = []
    for _ in range(2):
        field = ndimage.gaussian_filter(rng.normal(size=(18, 20, 22)), 3)
        mask = field > np.percentile(field, 70)
        mask[[0, -1]] = mask[:, [0, -1]] = mask[:, :, [0, -1]] = False
        masks.append(mask)
    direction = sitk.VersorTransform((0.3, 0.2, 0.9), 0.5).GetMatrix()
    images = [_image(m, direction=direction) for m in masks]

    def directed(src, dst):
        tree = cKDTree(voxel_to_physical(images[0], np.argwhere(_border(dst))))
        return tree.query(voxel_to_physical(images[0], np.argwhere(_border(src))))[0]

    pooled = np.concatenate([directed(masks[0], masks[1]), directed(masks[1], masks[0])])
    assert hd95(*images) == pytest.approx(np.percentile(pooled, 95), rel=1e-6)
    assert assd(*images) == pytest.approx(pooled.mean(), rel=1e-6)


def test_empty_masks():
    empty = np.zeros((5, 5, 5), np.uint8)
    full = empty.copy()
    full[2, 2, 2] = 1
    assert math.isnan(dice(_image(empty), _image(empty)))
    assert math.isnan(hd95(_image(empty), _image(empty)))
    assert dice(_image(empty), _image(full)) == 0.0
    assert hd95(_image(empty), _image(full)) == math.inf


def test_grids_must_match():
    a = np.zeros((5, 5, 5), np.uint8)
    with pytest.raises(ImageGeometryError, match="different grids"):
        dice(_image(a), _image(a, spacing=(1.0, 1.0, 1.0)))


def test_landmark_error_in_mm_and_voxels():
    image = _image(np.zeros((4, 4, 4)))
    estimated = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 4.0]])
    reference = np.zeros((2, 3))
    mm, vox = landmark_errors(estimated, reference, image)
    np.testing.assert_allclose(mm, [1.0, 4.0])
    np.testing.assert_allclose(vox, [2.0, 2.0])  # 1 mm at 0.5 mm in x; 4 mm at 2 mm in z
    with pytest.raises(ImageGeometryError):
        landmark_errors(estimated, reference[:1])


def test_dice_per_label_scores_each_value_of_the_reference_and_the_union_binarises():
    reference = sitk.GetImageFromArray(np.array([[[1, 1, 2, 2, 0, 0]]], dtype=np.uint8))
    prediction = sitk.GetImageFromArray(np.array([[[1, 2, 2, 2, 0, 0]]], dtype=np.uint8))
    assert dice_per_label(prediction, reference) == {1: pytest.approx(2 / 3), 2: 0.8}
    # the union's scores see one structure: no boundary between its labels
    scores = score_segmentation(prediction, reference)
    assert scores.dice == 1.0 and scores.hd95 == 0.0
