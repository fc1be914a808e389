"""Label maps: read and check against their image, select labels."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import SimpleITK as sitk

from medseg.errors import LabelError
from medseg.io._checks import INTEGER_PIXELS, check_same_geometry, describe
from medseg.io._images import read_image

__all__ = ["label_values", "read_label", "select_labels"]


def read_label(source: Any, reference: Any = None, *, name: str | None = None) -> sitk.Image:
    """Read a label map and check it against its image.

    Parameters
    ----------
    source : path-like, SimpleITK.Image or nibabel image
        The label map (anything :func:`read_image` accepts).
    reference : path-like, SimpleITK.Image or nibabel image, optional
        The image the labels belong to. Size must be equal; spacing, origin and direction
        equal to 1e-4 relative (see :func:`check_same_geometry`). Within tolerance, the
        reference's geometry is copied onto the label map, so the two agree exactly.
    name : str, optional
        Name of the label map for error messages.

    Returns
    -------
    label : SimpleITK.Image
        Integer pixel type. Integer files keep their type; float files whose values are all
        integral are cast to the smallest unsigned type that holds them.

    Raises
    ------
    LabelError
        Non-integral or negative values, or geometry different from ``reference``.
    InputFileError, ImageFormatError, ImageGeometryError
        As :func:`read_image`.
    """
    label_name = describe(source, name)
    label = read_image(source, name=label_name)
    values = sitk.GetArrayViewFromImage(label)
    if label.GetPixelID() not in INTEGER_PIXELS:
        if not np.array_equal(values, np.round(values)):
            raise LabelError(
                f"{label_name}: label map has non-integral values "
                f"({label.GetPixelIDTypeAsString()}); is this an intensity image, or was it "
                "resampled with linear interpolation? Use nearest neighbour for labels"
            )
    low, high = (values.min(), values.max()) if values.size else (0, 0)
    if low < 0:
        raise LabelError(f"{label_name}: label map has negative values (min {low})")
    if label.GetPixelID() not in INTEGER_PIXELS:
        target = next(
            (
                pid
                for pid, dtype in (
                    (sitk.sitkUInt8, np.uint8),
                    (sitk.sitkUInt16, np.uint16),
                    (sitk.sitkUInt32, np.uint32),
                )
                if high <= np.iinfo(dtype).max
            ),
            None,
        )
        if target is None:
            raise LabelError(
                f"{label_name}: label map has values up to {high:.6g}, too large to be labels "
                f"(the limit is {np.iinfo(np.uint32).max}); is this an intensity image?"
            )
        label = sitk.Cast(label, target)
    if reference is not None:
        ref_name = describe(reference)
        ref = reference if isinstance(reference, sitk.Image) else read_image(reference)
        problems = check_same_geometry(label, ref)
        if problems:
            raise LabelError(
                f"label map {label_name} does not match its image {ref_name}: "
                + "; ".join(problems)
                + ". Resample it onto the image with "
                "medseg.io.resample_like(label, image, is_label=True) if that is intended"
            )
        if label is source:  # do not change the caller's image in place
            label = sitk.Image(label)
        label.CopyInformation(ref)
    return label


def select_labels(
    label_image: Any, labels: int | Iterable[int], *, name: str | None = None
) -> sitk.Image:
    """Binary mask of the union of some labels.

    Parameters
    ----------
    label_image : 3D SimpleITK image with integer voxels
        Or anything :func:`read_label` accepts (path, nibabel image).
    labels : int or iterable of int
        Label values to keep, e.g. ``(1, 2)`` for the whole MSD hippocampus.
    name : str, optional
        Name of the label map for the error message (default: its path if given one).

    Returns
    -------
    mask : SimpleITK.Image
        uint8, 1 inside the union of ``labels``, 0 elsewhere; same geometry as
        ``label_image``.

    Raises
    ------
    LabelError
        The mask is empty: none of ``labels`` occurs. The message lists the labels that do.
    """
    if isinstance(label_image, sitk.Image):
        label_name = name or "label map"
    else:
        label_name = describe(label_image, name)
        label_image = read_label(label_image, name=label_name)
    wanted = [int(labels)] if np.isscalar(labels) else [int(v) for v in labels]
    values = sitk.GetArrayViewFromImage(label_image)
    mask = np.isin(values, wanted)
    if not mask.any():
        present = [int(v) for v in np.unique(values)]
        raise LabelError(
            f"{label_name} has none of the labels {wanted} (empty mask); labels present: "
            f"{present}. Check the label numbers (dataset.json) or the file"
        )
    out = sitk.GetImageFromArray(mask.astype(np.uint8))
    out.CopyInformation(label_image)
    return out


def label_values(label_map: sitk.Image, labels: int | Iterable[int]) -> sitk.Image:
    """``label_map`` with the values outside ``labels`` set to 0; a single label becomes 1.

    The label map a segmenter learns and returns: the training labels' own values (the
    hippocampus' 1 anterior, 2 posterior) when there are several, 1 for one (uint8).
    """
    values = sitk.GetArrayFromImage(label_map)
    wanted = [int(labels)] if np.isscalar(labels) else [int(v) for v in labels]
    if len(wanted) > 1 and max(wanted) > 255:
        raise LabelError(f"label values {wanted} do not fit a uint8 label map (at most 255)")
    kept = np.where(np.isin(values, wanted), values, 0)
    if len(wanted) == 1:
        kept = (kept > 0).astype(np.uint8)
    out = sitk.GetImageFromArray(kept.astype(np.uint8))
    out.CopyInformation(label_map)
    return out
