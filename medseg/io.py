"""Images, landmark files and atomic writes.

* Images: :func:`read_image` / :func:`write_image` for NIfTI (``.nii``, ``.nii.gz``), NRRD,
  MetaImage (``.mha``, ``.mhd``) and DICOM series folders, through SimpleITK; nibabel images
  are accepted everywhere and given back with :func:`to_nibabel` / :func:`as_input_type`.
  Label maps: :func:`read_label`, :func:`select_labels`, :func:`resample_like`.
* Landmarks: :func:`read_landmarks` / :func:`write_landmarks` (CSV, Slicer ``.fcsv`` and
  ``.mrk.json``).
* Every write goes through :func:`atomic_write`.

Conventions (see the design notes):

* Points (landmarks, surface vertices) are float arrays of shape ``(N, 3)`` in physical
  millimetres, ``(x, y, z)`` order, in the image's world frame (ITK / LPS).
* Voxel arrays are SimpleITK's ``(z, y, x)`` numpy views. Convert between array indices and
  physical points only with :func:`voxel_to_physical` and :func:`physical_to_voxel`.
* nibabel affines are RAS+, ITK is LPS: the conversion (x and y negated) happens only in
  :func:`read_image` (nibabel in) and :func:`to_nibabel` (nibabel out).

What is checked, beyond SimpleITK: a truncated NIfTI file (ITK reads it without complaint),
NIfTI-2 files (this ITK cannot read them; nibabel does), sheared affines (ITK would silently
orthogonalise them), non-finite voxels, label maps off their image's grid.

Examples
--------
>>> from medseg import io
>>> image = io.read_image("case_0000.nii.gz")  # doctest: +SKIP
>>> label = io.read_label("case.nii.gz", reference=image)  # doctest: +SKIP
>>> mask = io.select_labels(label, (1, 2))  # doctest: +SKIP
>>> io.write_image(mask, "out/case.nii.gz", like=image)  # doctest: +SKIP
>>> points = io.read_landmarks("case.mrk.json")  # (N, 3) mm, LPS  # doctest: +SKIP
>>> zyx = io.physical_to_voxel(image, points)  # doctest: +SKIP
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from numpy.typing import ArrayLike

from medseg._io_atomic import atomic_folder, atomic_write, check_not_protected
from medseg._io_checks import check_image, check_same_geometry
from medseg._io_dicom import write_dicom_series
from medseg._io_images import IMAGE_SUFFIXES, image_suffix, read_image, write_image
from medseg._io_labels import read_label, resample_like, select_labels
from medseg._io_landmarks import LANDMARK_SUFFIXES, read_landmarks, write_landmarks
from medseg._io_nibabel import as_input_type, to_nibabel

__all__ = [
    "voxel_to_physical",
    "physical_to_voxel",
    "image_geometry",
    "IMAGE_SUFFIXES",
    "LANDMARK_SUFFIXES",
    "image_suffix",
    "read_image",
    "read_label",
    "select_labels",
    "resample_like",
    "check_image",
    "check_same_geometry",
    "to_nibabel",
    "as_input_type",
    "write_image",
    "write_dicom_series",
    "read_landmarks",
    "write_landmarks",
    "atomic_folder",
    "atomic_write",
    "check_not_protected",
]


def _affine(image: sitk.Image) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(A, origin)`` with ``physical = origin + A @ ijk`` for ITK index ``ijk``."""
    direction = np.asarray(image.GetDirection(), dtype=float).reshape(3, 3)
    spacing = np.asarray(image.GetSpacing(), dtype=float)
    return direction * spacing[None, :], np.asarray(image.GetOrigin(), dtype=float)


def voxel_to_physical(image: sitk.Image, zyx: ArrayLike) -> np.ndarray:
    """Physical positions of array indices.

    Parameters
    ----------
    image : 3D SimpleITK image
        Supplies spacing, origin and direction.
    zyx : (N, 3) or (3,) array
        Indices into ``sitk.GetArrayFromImage(image)`` in ``(z, y, x)`` order, as returned by
        ``np.argwhere``; may be fractional (continuous index).

    Returns
    -------
    points : (N, 3) or (3,) float array, mm, (x, y, z)
    """
    zyx = np.asarray(zyx, dtype=float)
    a, origin = _affine(image)
    ijk = zyx[..., ::-1]
    return ijk @ a.T + origin


def physical_to_voxel(image: sitk.Image, points: ArrayLike) -> np.ndarray:
    """Continuous array indices ``(z, y, x)`` of physical points; inverse of
    :func:`voxel_to_physical`.

    Parameters
    ----------
    image : 3D SimpleITK image
    points : (N, 3) or (3,) float array, mm, (x, y, z)

    Returns
    -------
    zyx : (N, 3) or (3,) float array
        Continuous indices into the ``(z, y, x)`` voxel array; round them to get a voxel.
    """
    points = np.asarray(points, dtype=float)
    a, origin = _affine(image)
    ijk = np.linalg.solve(a, (points - origin).reshape(-1, 3).T).T.reshape(points.shape)
    return ijk[..., ::-1]


def image_geometry(image: sitk.Image) -> dict:
    """Size, spacing, origin and direction of an image as plain tuples (JSON-friendly)."""
    return {
        "size": tuple(int(s) for s in image.GetSize()),
        "spacing": tuple(float(s) for s in image.GetSpacing()),
        "origin": tuple(float(s) for s in image.GetOrigin()),
        "direction": tuple(float(s) for s in image.GetDirection()),
    }
