"""Checks shared by medseg.io: usable 3D images, equal geometry, readable error names."""

from __future__ import annotations

import os
from typing import Any

import nibabel as nib
import numpy as np
import SimpleITK as sitk

from medseg.errors import ImageGeometryError

__all__ = [
    "INTEGER_PIXELS",
    "FLOAT_PIXELS",
    "describe",
    "is_nibabel",
    "itk_reason",
    "check_direction",
    "check_image",
    "check_finite",
    "check_same_geometry",
]

INTEGER_PIXELS = {
    sitk.sitkUInt8,
    sitk.sitkInt8,
    sitk.sitkUInt16,
    sitk.sitkInt16,
    sitk.sitkUInt32,
    sitk.sitkInt32,
    sitk.sitkUInt64,
    sitk.sitkInt64,
}
FLOAT_PIXELS = {sitk.sitkFloat32, sitk.sitkFloat64}


def describe(source: Any, name: str | None = None) -> str:
    """A name for ``source`` to use in error messages."""
    if name:
        return str(name)
    if isinstance(source, str | os.PathLike):
        return str(source)
    if isinstance(source, nib.spatialimages.SpatialImage):
        filename = source.get_filename()
        return filename if filename else f"the given nibabel {type(source).__name__}"
    return "the given SimpleITK image"


def is_nibabel(obj: Any) -> bool:
    return isinstance(obj, nib.spatialimages.SpatialImage)


def itk_reason(exc: RuntimeError) -> str:
    """The informative last line of a SimpleITK exception (no C++ file paths)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return lines[-1] if lines else "unknown error"


def check_direction(direction: np.ndarray, name: str) -> None:
    """Raise ImageGeometryError unless ``direction`` is a finite, orthonormal 3x3 matrix."""
    if not np.all(np.isfinite(direction)) or abs(np.linalg.det(direction)) < 1e-6:
        raise ImageGeometryError(
            f"{name}: direction matrix {tuple(direction.ravel())} is singular or not finite; "
            "fix the image header (orientation)"
        )
    skew = np.abs(direction.T @ direction - np.eye(3)).max()
    if skew > 1e-4:
        raise ImageGeometryError(
            f"{name}: voxel axes are not perpendicular (sheared affine, |D^T D - I| = "
            f"{skew:.2g}); ITK would silently change this geometry. Resample the image onto "
            "an orthogonal grid first (e.g. nibabel.processing.resample_from_to)"
        )


def check_image(image: sitk.Image, *, name: str = "image") -> sitk.Image:
    """Check that ``image`` is a usable 3D scalar image; return it unchanged.

    Raises
    ------
    ImageGeometryError
        Not 3D, more than one component per voxel, a single slice, non-positive or
        non-finite spacing, a singular, sheared or non-finite direction, non-finite origin
        or voxels, float64 voxels beyond the float32 range (medseg computes in float32).
    """
    dim = image.GetDimension()
    if dim != 3:
        raise ImageGeometryError(
            f"{name}: image is {dim}D (size {image.GetSize()}); medseg needs a 3D image"
            + (" (a 4D series: pick one volume first)" if dim == 4 else "")
        )
    ncomp = image.GetNumberOfComponentsPerPixel()
    if ncomp != 1 or image.GetPixelID() in (sitk.sitkComplexFloat32, sitk.sitkComplexFloat64):
        raise ImageGeometryError(
            f"{name}: image has {image.GetPixelIDTypeAsString()} voxels with {ncomp} "
            "component(s); medseg needs a single-channel scalar 3D image "
            "(extract one channel, e.g. with sitk.VectorIndexSelectionCast)"
        )
    size = image.GetSize()
    if min(size) < 2:
        raise ImageGeometryError(
            f"{name}: image size {size} has a single voxel along an axis; "
            "medseg needs a 3D volume, not a slice"
        )
    spacing = np.asarray(image.GetSpacing(), dtype=float)
    if not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise ImageGeometryError(
            f"{name}: voxel spacing {tuple(spacing)} must be finite and positive"
        )
    if not np.all(np.isfinite(image.GetOrigin())):
        raise ImageGeometryError(f"{name}: origin {image.GetOrigin()} is not finite")
    check_direction(np.asarray(image.GetDirection(), dtype=float).reshape(3, 3), name)
    if image.GetPixelID() in FLOAT_PIXELS:
        values = sitk.GetArrayViewFromImage(image)
        check_finite(values, name)
        if image.GetPixelID() == sitk.sitkFloat64 and values.size:
            peak = float(np.abs(values).max())
            if peak > _FLOAT32_MAX:
                raise ImageGeometryError(
                    f"{name}: voxel values reach {peak:.3g}, beyond the float32 range "
                    f"(+-{_FLOAT32_MAX:.3g}) medseg computes in; rescale the image"
                )
    return image


_FLOAT32_MAX = float(np.finfo(np.float32).max)


def check_finite(values: np.ndarray, name: str, *, note: str = "") -> None:
    """Raise ImageGeometryError if a ``(z, y, x)`` voxel array holds NaN or infinite values."""
    finite = np.isfinite(values)
    if not finite.all():
        n_bad = int(finite.size - np.count_nonzero(finite))
        first = tuple(int(i) for i in np.argwhere(~finite)[0])
        raise ImageGeometryError(
            f"{name}: {n_bad} voxel(s) are NaN or infinite (first at (z, y, x) = {first}){note}; "
            "replace them (e.g. with 0) before using the image"
        )


def check_same_geometry(
    image: sitk.Image, reference: sitk.Image, *, rtol: float = 1e-4
) -> list[str]:
    """Differences in geometry between two images, as readable strings (empty if same).

    Size must be equal; spacing equal to ``rtol`` relative; origin equal to ``rtol`` times
    the largest voxel size (or ``rtol`` mm, whichever is larger); direction cosines equal to
    ``rtol``.
    """
    problems = []
    if image.GetSize() != reference.GetSize():
        problems.append(f"size {image.GetSize()} vs {reference.GetSize()}")
    sp, sp_ref = np.asarray(image.GetSpacing()), np.asarray(reference.GetSpacing())
    if not np.allclose(sp, sp_ref, rtol=rtol, atol=0.0):
        problems.append(f"spacing {tuple(sp)} vs {tuple(sp_ref)}")
    o, o_ref = np.asarray(image.GetOrigin()), np.asarray(reference.GetOrigin())
    if not np.allclose(o, o_ref, rtol=0.0, atol=rtol * max(1.0, float(sp_ref.max()))):
        problems.append(f"origin {tuple(o)} vs {tuple(o_ref)}")
    d, d_ref = np.asarray(image.GetDirection()), np.asarray(reference.GetDirection())
    if not np.allclose(d, d_ref, rtol=0.0, atol=rtol):
        problems.append(f"direction {tuple(d)} vs {tuple(d_ref)}")
    return problems
