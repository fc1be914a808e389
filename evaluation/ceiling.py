"""The ceiling of the landmark representation: what perfect landmarks would give.

A fitted segmenter's template carried by its thin-plate spline onto a test case's
*reference* landmarks (:func:`medseg.evaluation.references.fold_landmarks`: the training
correspondence transferred onto the case's true label map), with and without the regional
stage. No landmark detector can do better than the template this way, so the gap between a
method and its ceiling is what the landmarks cost, and the ceiling itself what the template
and the stage can represent. It reads the reference, so it is a yardstick, never a method a
user could run.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from medseg.reconstruction import warp_labels

__all__ = ["CeilingResult", "reference_ceiling"]


@dataclass
class CeilingResult:
    """A label map on the input's grid; ``landmarks`` is None (they are the reference)."""

    label: sitk.Image
    landmarks: None = None


def reference_ceiling(
    segmenter, image: sitk.Image, reference_landmarks: np.ndarray | None, *, boundary: bool
) -> CeilingResult | None:
    """The segmenter's template warped onto ``reference_landmarks`` in ``image``'s grid.

    Parameters
    ----------
    segmenter : fitted estimator
        With ``template_mask_`` and ``template_landmarks_`` (the shape-prior segmenter, the
        ASM baseline); for ``boundary=True`` also ``frame_`` and a fitted ``boundary_``.
    image : SimpleITK image
    reference_landmarks : (N, 3) array in mm, or None
    boundary : bool
        Refine the warped template with the segmenter's regional stage.

    Returns
    -------
    CeilingResult or None
        None when there is no reference, its landmarks do not match the template's, or
        ``boundary`` is asked of a segmenter without a stage: there is no ceiling to score.
    """
    if reference_landmarks is None:
        return None
    reference = np.asarray(reference_landmarks, dtype=float)
    template = np.asarray(segmenter.template_landmarks_, dtype=float)
    if reference.shape != template.shape:
        return None
    if boundary:
        stage = getattr(segmenter, "boundary_", None)
        if stage is None:
            return None
        refined = stage.refine(
            segmenter.frame_, segmenter.template_mask_, template, image, reference
        )
        return CeilingResult(label=refined.label)
    smoothing = float(getattr(segmenter, "smoothing", 0.0))
    label = warp_labels(segmenter.template_mask_, template, reference, image, smoothing=smoothing)
    return CeilingResult(label=label)
