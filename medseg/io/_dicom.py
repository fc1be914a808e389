"""DICOM series: read a folder (one series, or the one asked for); write one slice per file."""

from __future__ import annotations

import os
import secrets
import shutil
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from medseg.errors import ImageFormatError, ImageGeometryError, InputFileError
from medseg.io._atomic import PathLike, check_not_protected
from medseg.io._checks import check_image, describe, is_nibabel, itk_reason
from medseg.io._nibabel import from_nibabel

__all__ = ["read_dicom_folder", "write_dicom_series"]

_DICOM_PIXELS = {sitk.sitkUInt8, sitk.sitkInt8, sitk.sitkUInt16, sitk.sitkInt16}


def read_dicom_folder(folder: Path, series_id: str | None = None) -> sitk.Image:
    """Read the DICOM series in ``folder`` (slices sorted by position, by GDCM).

    Raises :class:`~medseg.errors.ImageFormatError` if the folder holds no series, several
    series and no ``series_id``, or unreadable files. Checks come after, in ``read_image``.
    """
    try:
        ids = sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(folder))
    except RuntimeError as exc:
        raise ImageFormatError(f"{str(folder)!r}: cannot scan for DICOM files: {exc}") from exc
    if not ids:
        raise ImageFormatError(
            f"{str(folder)!r}: folder holds no DICOM series; give an image file "
            "(.nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd, .dcm) or a folder of DICOM slices"
        )
    if series_id is None:
        if len(ids) > 1:
            raise ImageFormatError(
                f"{str(folder)!r}: folder holds {len(ids)} DICOM series {tuple(ids)}; "
                "pass series_id= to choose one"
            )
        series_id = ids[0]
    elif series_id not in ids:
        raise ImageFormatError(
            f"{str(folder)!r}: no DICOM series {series_id!r}; it holds {tuple(ids)}"
        )
    files = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), series_id)
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    try:
        return reader.Execute()
    except RuntimeError as exc:
        raise ImageFormatError(
            f"{str(folder)!r}: DICOM series {series_id!r} is unreadable: {itk_reason(exc)}"
        ) from exc


def _new_uid() -> str:
    """A random DICOM UID (UUID-derived, under the 2.25 root; at most 64 characters)."""
    return "2.25." + str(int.from_bytes(secrets.token_bytes(16), "big"))


def _ds(values: Iterable[float]) -> str:
    """DICOM decimal strings (at most 16 characters each), backslash-separated."""
    return "\\".join(f"{float(v):.10g}" for v in values)


def write_dicom_series(
    image: Any,
    folder: PathLike,
    *,
    protect: Iterable[PathLike] = (),
    series_description: str = "medseg",
) -> Path:
    """Write a 3D image as a DICOM series, one file per slice, atomically.

    Parameters
    ----------
    image : SimpleITK.Image or nibabel image
        Integer voxels (uint8, int8, uint16, int16): DICOM stores no floats. The direction
        must be right-handed (det > 0): a DICOM series has its slice normal fixed by the row
        and column directions, so a mirrored image would read back re-ordered.
    folder : path-like
        A new (or empty) folder; it is written as ``.tmp-<random>-<name>.part`` beside it, then
        renamed. Files are ``slice_0000.dcm``, ... in slice order.
    protect : iterable of path-like
        Inputs that must not be replaced (e.g. the folder the image was read from).
    series_description : str
        DICOM Series Description (0008,103E).

    Returns
    -------
    folder : pathlib.Path
        Read it back with :func:`read_image`.
    """
    folder = Path(folder)
    image = check_image(
        from_nibabel(image, describe(image)) if is_nibabel(image) else image, name=str(folder)
    )
    check_not_protected(folder, protect)
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise InputFileError(
            f"{str(folder)!r} exists and is not an empty folder; choose a new folder for the "
            "DICOM series"
        )
    if image.GetPixelID() not in _DICOM_PIXELS:
        raise ImageFormatError(
            f"cannot write {str(folder)!r} as DICOM: voxels are "
            f"{image.GetPixelIDTypeAsString()}; cast to int16 or uint16 first "
            "(DICOM stores integers)"
        )
    direction = np.asarray(image.GetDirection(), dtype=float).reshape(3, 3)
    if np.linalg.det(direction) <= 0:
        raise ImageGeometryError(
            f"cannot write {str(folder)!r} as DICOM: the direction matrix is left-handed "
            "(mirrored); write NIfTI or NRRD instead, or flip the image"
        )
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = folder.parent / f".tmp-{secrets.token_hex(6)}-{folder.name}.part"
    tmp.mkdir()
    try:
        study, series, frame = _new_uid(), _new_uid(), _new_uid()
        now = time.gmtime()
        common = {
            "0008|0020": time.strftime("%Y%m%d", now),  # study date
            "0008|0021": time.strftime("%Y%m%d", now),  # series date
            "0008|0031": time.strftime("%H%M%S", now),  # series time
            "0008|0008": "DERIVED\\SECONDARY",  # image type
            "0008|0060": "OT",  # modality: other
            "0008|103e": series_description,
            "0020|000d": study,
            "0020|000e": series,
            "0020|0052": frame,  # frame of reference
            "0020|0037": _ds(np.r_[direction[:, 0], direction[:, 1]]),  # orientation
            "0018|0050": _ds([image.GetSpacing()[2]]),  # slice thickness
            "0028|0030": _ds(
                [image.GetSpacing()[1], image.GetSpacing()[0]]
            ),  # pixel spacing: between rows, between columns
        }
        writer = sitk.ImageFileWriter()
        writer.KeepOriginalImageUIDOn()
        writer.SetImageIO("GDCMImageIO")
        for k in range(image.GetSize()[2]):
            piece = image[:, :, k]
            for tag, value in common.items():
                piece.SetMetaData(tag, value)
            piece.SetMetaData("0008|0018", _new_uid())  # SOP instance UID
            piece.SetMetaData("0020|0013", str(k + 1))  # instance number
            position = image.TransformIndexToPhysicalPoint((0, 0, k))
            piece.SetMetaData("0020|0032", _ds(position))
            writer.SetFileName(str(tmp / f"slice_{k:04d}.dcm"))
            try:
                writer.Execute(piece)
            except RuntimeError as exc:
                raise InputFileError(
                    f"cannot write DICOM series {str(folder)!r}: {itk_reason(exc)}"
                ) from exc
        if folder.is_dir():
            folder.rmdir()  # empty, checked above
        os.replace(tmp, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder
