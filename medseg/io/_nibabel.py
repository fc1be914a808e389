"""nibabel interop: RAS+ affines in and out, converted to and from ITK's LPS exactly once."""

from __future__ import annotations

from typing import Any

import nibabel as nib
import numpy as np
import SimpleITK as sitk

from medseg.errors import ImageGeometryError
from medseg.io._checks import check_direction, is_nibabel

__all__ = ["from_nibabel", "to_nibabel", "as_input_type"]

# nibabel affines map to RAS+ world coordinates, ITK to LPS: flip x and y, once, here.
_RAS_LPS = np.diag([-1.0, -1.0, 1.0])


def from_nibabel(img: nib.spatialimages.SpatialImage, name: str) -> sitk.Image:
    """SimpleITK image with the same voxels and world positions as a nibabel image."""
    data = np.asanyarray(img.dataobj)
    while data.ndim > 3 and data.shape[-1] == 1:  # as ITK does: drop trailing unit axes
        data = data[..., 0]
    if data.ndim != 3:
        raise ImageGeometryError(
            f"{name}: image is {data.ndim}D (shape {data.shape}); medseg needs a 3D image"
        )
    if not data.dtype.isnative:  # big-endian files: SimpleITK takes native order only
        data = data.astype(data.dtype.newbyteorder("="))
    if data.dtype == bool:
        data = data.astype(np.uint8)
    elif data.dtype == np.float16:
        data = data.astype(np.float32)
    elif data.dtype.fields is not None or data.dtype.kind == "c":
        raise ImageGeometryError(
            f"{name}: voxels of type {data.dtype} (RGB or complex); medseg needs scalar voxels"
        )
    affine = np.asarray(img.affine, dtype=float)
    if affine.shape != (4, 4) or not np.all(np.isfinite(affine)):
        raise ImageGeometryError(f"{name}: affine is missing or not finite:\n{affine}")
    linear = _RAS_LPS @ affine[:3, :3]
    spacing = np.linalg.norm(linear, axis=0)
    if np.any(spacing <= 0):
        raise ImageGeometryError(
            f"{name}: affine gives voxel spacing {tuple(spacing)}; spacing must be positive"
        )
    direction = linear / spacing
    check_direction(direction, name)
    image = sitk.GetImageFromArray(np.ascontiguousarray(data.transpose(2, 1, 0)), isVector=False)
    try:
        image.SetSpacing(tuple(float(s) for s in spacing))
        image.SetOrigin(tuple(float(v) for v in _RAS_LPS @ affine[:3, 3]))
        image.SetDirection(tuple(float(v) for v in direction.ravel()))
    except RuntimeError as exc:
        raise ImageGeometryError(f"{name}: unusable affine:\n{affine}") from exc
    return image


def to_nibabel(image: sitk.Image, *, like: Any = None) -> nib.Nifti1Image:
    """Convert a SimpleITK image to a nibabel NIfTI image with the same world positions.

    Parameters
    ----------
    image : 3D SimpleITK image
        Geometry in ITK's LPS world frame.
    like : nibabel image, optional
        If a ``Nifti2Image``, a ``Nifti2Image`` is returned; its spatial/temporal units
        are kept. Otherwise a ``Nifti1Image``.

    Returns
    -------
    nibabel.Nifti1Image or nibabel.Nifti2Image
        Data of shape ``image.GetSize()`` (x, y, z order, i.e. the SimpleITK array
        transposed), affine mapping voxel (i, j, k) to RAS+ millimetres (x and y of the LPS
        point negated), qform and sform codes 1 (scanner).
    """
    if image.GetDimension() != 3 or image.GetNumberOfComponentsPerPixel() != 1:
        raise ImageGeometryError(
            f"to_nibabel needs a 3D scalar image, got {image.GetDimension()}D with "
            f"{image.GetNumberOfComponentsPerPixel()} component(s)"
        )
    direction = np.asarray(image.GetDirection(), dtype=float).reshape(3, 3)
    spacing = np.asarray(image.GetSpacing(), dtype=float)
    affine = np.eye(4)
    affine[:3, :3] = _RAS_LPS @ (direction * spacing[None, :])
    affine[:3, 3] = _RAS_LPS @ np.asarray(image.GetOrigin(), dtype=float)
    data = sitk.GetArrayFromImage(image).transpose(2, 1, 0)
    cls = nib.Nifti2Image if isinstance(like, nib.Nifti2Image) else nib.Nifti1Image
    out = cls(data, affine, dtype=data.dtype)
    # header fields are float32 (NIfTI); the in-memory affine stays exact float64
    out.set_qform(affine, code=1, update_affine=False)
    out.set_sform(affine, code=1, update_affine=False)
    units = ("mm", "sec")
    if isinstance(like, nib.Nifti1Image | nib.Nifti2Image):
        units = like.header.get_xyzt_units()
    out.header.set_xyzt_units(*units)
    return out


def as_input_type(image: sitk.Image, *, like: Any) -> sitk.Image | nib.Nifti1Image:
    """Return ``image`` in the type of the caller's input ``like``.

    A notebook that passed a nibabel image gets a nibabel image back (through
    :func:`to_nibabel`); anything else (SimpleITK image, path) gets the SimpleITK image.
    """
    if is_nibabel(like):
        return to_nibabel(image, like=like)
    return image
