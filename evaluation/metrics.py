"""Segmentation and landmark metrics, in millimetres, spacing- and direction-aware.

* Dice overlap of two binary masks (NaN when both are empty, as in nnU-Net);
* HD95 and ASSD between the boundaries of two masks: distances from every boundary voxel
  of one mask to the boundary of the other, with SimpleITK's Maurer distance transform in
  physical units. HD95 is the 95th percentile of the pooled distances of both directions
  (the medpy / MSD definition); ASSD is their mean;
* landmark error: Euclidean distance per landmark in mm, and in voxels of the test image
  (the displacement expressed in continuous voxel indices).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
from numpy.typing import ArrayLike

from medseg.errors import ImageGeometryError
from medseg.io import check_same_geometry, physical_to_voxel

__all__ = [
    "dice",
    "dice_per_label",
    "surface_distances",
    "hd95",
    "assd",
    "landmark_errors",
    "SegmentationScores",
    "score_segmentation",
]


def _mask(image: sitk.Image) -> sitk.Image:
    return sitk.Cast(image > 0, sitk.sitkUInt8)


def _check_same_grid(a: sitk.Image, b: sitk.Image) -> None:
    problems = check_same_geometry(a, b)
    if problems:
        raise ImageGeometryError(
            f"the two label maps are on different grids ({'; '.join(problems)}); "
            "resample the prediction onto the reference first"
        )


def dice(prediction: sitk.Image, reference: sitk.Image) -> float:
    """Dice overlap of the non-zero voxels; NaN when both masks are empty."""
    _check_same_grid(prediction, reference)
    a = sitk.GetArrayViewFromImage(prediction) > 0
    b = sitk.GetArrayViewFromImage(reference) > 0
    total = int(a.sum()) + int(b.sum())
    if total == 0:
        return float("nan")
    return 2.0 * float(np.logical_and(a, b).sum()) / total


def dice_per_label(prediction: sitk.Image, reference: sitk.Image) -> dict[int, float]:
    """Dice overlap of each non-zero value of ``reference`` (a label map of sub-labels, e.g.
    the hippocampus' 1 anterior and 2 posterior) with the same value in ``prediction``."""
    _check_same_grid(prediction, reference)
    a, b = sitk.GetArrayViewFromImage(prediction), sitk.GetArrayViewFromImage(reference)
    out = {}
    for value in (int(v) for v in np.unique(b) if v):
        p, r = a == value, b == value
        out[value] = 2.0 * float(np.logical_and(p, r).sum()) / (int(p.sum()) + int(r.sum()))
    return out


def _directed(from_mask: sitk.Image, to_mask: sitk.Image) -> np.ndarray:
    """Distances (mm) from each boundary voxel of ``from_mask`` to the boundary of ``to_mask``."""
    # GetArrayFromImage (a copy): a view of a temporary image would dangle.
    from_border = sitk.GetArrayFromImage(sitk.LabelContour(from_mask, fullyConnected=True))
    to_border = sitk.LabelContour(to_mask, fullyConnected=True)
    distance = sitk.SignedMaurerDistanceMap(
        to_border, insideIsPositive=False, squaredDistance=False, useImageSpacing=True
    )
    # The signed map is negative inside the 1-voxel-thick border; distance to it is |d| there
    # and zero on it.
    values = np.abs(sitk.GetArrayFromImage(distance))
    values[sitk.GetArrayFromImage(to_border) > 0] = 0.0
    return values[from_border > 0].astype(float)


def surface_distances(prediction: sitk.Image, reference: sitk.Image) -> np.ndarray:
    """Pooled boundary-to-boundary distances (mm) of both directions.

    Returns an empty array when both masks are empty, and ``[inf]`` when exactly one is.
    """
    _check_same_grid(prediction, reference)
    a, b = _mask(prediction), _mask(reference)
    empty_a = not sitk.GetArrayFromImage(a).any()
    empty_b = not sitk.GetArrayFromImage(b).any()
    if empty_a and empty_b:
        return np.empty(0)
    if empty_a or empty_b:
        return np.array([np.inf])
    return np.concatenate([_directed(a, b), _directed(b, a)])


def _percentile95(d: np.ndarray) -> float:
    if not d.size:
        return float("nan")
    return float("inf") if np.isinf(d).any() else float(np.percentile(d, 95))


def _mean(d: np.ndarray) -> float:
    return float(d.mean()) if d.size else float("nan")


def hd95(prediction: sitk.Image, reference: sitk.Image) -> float:
    """95th-percentile symmetric Hausdorff distance (mm); NaN if both empty, inf if one is."""
    return _percentile95(surface_distances(prediction, reference))


def assd(prediction: sitk.Image, reference: sitk.Image) -> float:
    """Average symmetric surface distance (mm); NaN if both empty, inf if one is."""
    return _mean(surface_distances(prediction, reference))


def landmark_errors(
    estimated: ArrayLike, reference: ArrayLike, image: sitk.Image | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Per-landmark Euclidean error in mm and, given the test image, in voxels.

    Parameters
    ----------
    estimated, reference : (N, 3) float array, mm, (x, y, z)
    image : SimpleITK image, optional
        The test image; its spacing and direction convert the error to voxel units.

    Returns
    -------
    error_mm : (N,) float array
    error_voxels : (N,) float array or None
    """
    estimated = np.asarray(estimated, dtype=float)
    reference = np.asarray(reference, dtype=float)
    if estimated.shape != reference.shape or estimated.ndim != 2 or estimated.shape[1] != 3:
        raise ImageGeometryError(
            f"landmark arrays must both be (N, 3); got {estimated.shape} and {reference.shape}"
        )
    error_mm = np.linalg.norm(estimated - reference, axis=1)
    if image is None:
        return error_mm, None
    error_vox = np.linalg.norm(
        physical_to_voxel(image, estimated) - physical_to_voxel(image, reference), axis=1
    )
    return error_mm, error_vox


@dataclass(frozen=True)
class SegmentationScores:
    """Dice, HD95 (mm) and ASSD (mm) of one prediction."""

    dice: float
    hd95: float
    assd: float


def score_segmentation(prediction: sitk.Image, reference: sitk.Image) -> SegmentationScores:
    """Dice, HD95 and ASSD with the boundary distances computed once."""
    d = surface_distances(prediction, reference)
    return SegmentationScores(
        dice=dice(prediction, reference),
        hd95=_percentile95(d),
        assd=_mean(d),
    )
