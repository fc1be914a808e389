"""Images, landmark files and atomic writes.

* Images: :func:`read_image` / :func:`write_image` for NIfTI (``.nii``, ``.nii.gz``), NRRD,
  MetaImage (``.mha``, ``.mhd``) and DICOM series folders, through SimpleITK; nibabel images
  are accepted everywhere and given back with :func:`to_nibabel` / :func:`as_input_type`.
  Label maps: :func:`read_label`, :func:`select_labels`, :func:`label_values`,
  :func:`resample_like`.
* Landmarks: :func:`read_landmarks` / :func:`write_landmarks` (CSV, Slicer ``.fcsv`` and
  ``.mrk.json``).
* Fitted model parts: :func:`save_arrays` / :func:`load_arrays` (NPZ + JSON header).
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

from medseg.io._arrays import check_format, load_arrays, save_arrays
from medseg.io._atomic import atomic_folder, atomic_write, check_not_protected
from medseg.io._checks import check_image, check_same_geometry
from medseg.io._coordinates import image_geometry, physical_to_voxel, voxel_to_physical
from medseg.io._dicom import write_dicom_series
from medseg.io._images import (
    IMAGE_SUFFIXES,
    image_suffix,
    read_image,
    read_image_header,
    write_image,
)
from medseg.io._labels import label_values, read_label, select_labels
from medseg.io._landmarks import LANDMARK_SUFFIXES, read_landmarks, write_landmarks
from medseg.io._nibabel import as_input_type, to_nibabel
from medseg.io._resample import (
    FILLS,
    LABEL_INTERPOLATIONS,
    border_values,
    content_mask,
    padded_grid,
    random_pose,
    resample_affine,
    resample_like,
)

__all__ = [
    "voxel_to_physical",
    "physical_to_voxel",
    "image_geometry",
    "IMAGE_SUFFIXES",
    "LANDMARK_SUFFIXES",
    "image_suffix",
    "read_image",
    "read_image_header",
    "read_label",
    "select_labels",
    "label_values",
    "resample_like",
    "border_values",
    "resample_affine",
    "padded_grid",
    "content_mask",
    "random_pose",
    "FILLS",
    "LABEL_INTERPOLATIONS",
    "check_image",
    "check_same_geometry",
    "to_nibabel",
    "as_input_type",
    "write_image",
    "write_dicom_series",
    "read_landmarks",
    "write_landmarks",
    "save_arrays",
    "load_arrays",
    "check_format",
    "atomic_folder",
    "atomic_write",
    "check_not_protected",
]
