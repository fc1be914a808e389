"""Read and write 3D image files through SimpleITK, with the checks ITK does not make."""

from __future__ import annotations

import gzip
import math
import os
import sys
import zlib
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import nibabel as nib
import numpy as np
import SimpleITK as sitk

from medseg.errors import ImageFormatError, ImageGeometryError, InputFileError
from medseg.io._atomic import PathLike, atomic_write, check_not_protected
from medseg.io._checks import (
    check_finite,
    check_image,
    check_same_geometry,
    describe,
    is_nibabel,
    itk_reason,
)
from medseg.io._dicom import read_dicom_folder
from medseg.io._nibabel import from_nibabel, to_nibabel

__all__ = [
    "IMAGE_SUFFIXES",
    "READ_SUFFIXES",
    "image_suffix",
    "read_image",
    "read_image_header",
    "write_image",
]

#: Image file suffixes medseg reads and writes, with the ITK ImageIO that handles each.
#: Also read: a folder holding a DICOM series, and single (multi-frame) ``.dcm`` files.
IMAGE_SUFFIXES: dict[str, str] = {
    ".nii.gz": "NiftiImageIO",
    ".nii": "NiftiImageIO",
    ".nrrd": "NrrdImageIO",
    ".nhdr": "NrrdImageIO",
    ".mha": "MetaImageIO",
    ".mhd": "MetaImageIO",
}
READ_SUFFIXES = {**IMAGE_SUFFIXES, ".dcm": "GDCMImageIO"}
_COMPRESSIBLE = (".nrrd", ".nhdr", ".mha", ".mhd")


def image_suffix(path: PathLike) -> str | None:
    """The image-format suffix of ``path`` if medseg writes that format, else None.

    ``".nii.gz"`` counts as one suffix; the result is lower case, a key of
    :data:`IMAGE_SUFFIXES`.
    """
    name = Path(path).name.lower()
    return next((suffix for suffix in IMAGE_SUFFIXES if name.endswith(suffix)), None)


def _raw_suffix(path: PathLike) -> str:
    """The suffix as written (``.tar.gz``, ``.png``, ``.dcm``, ...), lower case."""
    name = Path(path).name.lower()
    for suffix in READ_SUFFIXES:
        if name.endswith(suffix):
            return suffix
    return "".join(Path(name).suffixes[-2:]) if name.endswith(".gz") else Path(name).suffix


def _unknown_format(path: PathLike, *, writing: bool = False) -> ImageFormatError:
    suffix = _raw_suffix(path)
    supported = tuple(IMAGE_SUFFIXES) if writing else (*READ_SUFFIXES, "a DICOM folder")
    return ImageFormatError(
        f"{str(path)!r}: unknown image format {suffix or '(no suffix)'!r}; "
        f"supported{' for writing' if writing else ''}: {', '.join(supported)}"
    )


def _check_nifti_complete(path: Path) -> nib.spatialimages.SpatialImage:
    """Raise ImageFormatError if a NIfTI file's header is unreadable or its data truncated.

    ITK reads a truncated NIfTI file without complaint (the missing voxels come back as
    garbage), so the byte count is checked here against the header. Returns the (lazily
    loaded) nibabel image.
    """
    try:
        with _quiet_nibabel():  # nibabel logs the header fixes it makes on stderr
            nimg = nib.load(path)
        header = nimg.header
        shape = tuple(int(n) for n in header.get_data_shape())
        # nibabel resets the header's vox_offset after loading; the proxy keeps the real one
        offset = int(getattr(nimg.dataobj, "offset", header.get_data_offset()))
        need = offset + math.prod(shape) * header.get_data_dtype().itemsize
    except Exception as exc:  # nibabel raises many types for a bad header
        raise ImageFormatError(
            f"{str(path)!r}: not a readable NIfTI file (corrupt or truncated header: {exc})"
        ) from exc
    if not shape or min(shape) < 1:
        raise ImageFormatError(
            f"{str(path)!r}: the NIfTI header declares image dimensions {shape}; a corrupt "
            "header: re-export or re-download the file"
        )
    if image_suffix(path) == ".nii.gz":
        # Fast path: the gzip trailer holds the uncompressed size mod 2**32. A truncated file
        # ends in deflate data instead, which matches the expected size with probability
        # 2**-32; corrupt deflate data (bit flips) makes ITK's own read fail.
        with open(path, "rb") as raw:
            raw.seek(0, os.SEEK_END)
            if raw.tell() >= 18:
                raw.seek(-4, os.SEEK_END)
                if int.from_bytes(raw.read(4), "little") == need % (1 << 32):
                    return nimg
        have = 0  # slow path (other total size, several gzip members): count every byte
        try:
            with gzip.open(path, "rb") as stream:
                while chunk := stream.read(1 << 22):
                    have += len(chunk)
        except (EOFError, OSError, zlib.error) as exc:
            raise ImageFormatError(
                f"{str(path)!r}: corrupt or truncated gzip data ({exc}); re-export or "
                "re-download the file"
            ) from exc
    else:
        have = path.stat().st_size
    if have < need:
        raise ImageFormatError(
            f"{str(path)!r}: truncated NIfTI file: {have} bytes of data, the header needs "
            f"{need}; re-export or re-download the file"
        )
    return nimg


@contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Keep what ITK's C++ readers print (niftilib, MetaIO, VNL, ITK warnings) off stderr.

    They write to the process's file descriptor 2 directly, so a corrupt file would print
    several lines before medseg's one-line error (the read's outcome is reported through
    the exception). The descriptor is redirected to /dev/null for the duration of the read.
    """
    warnings_shown = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no usable descriptor 2 (embedded interpreter)
        saved = None
    try:
        if saved is not None:
            with open(os.devnull, "w") as devnull:
                os.dup2(devnull.fileno(), 2)
        yield
    finally:
        if saved is not None:
            os.dup2(saved, 2)
            os.close(saved)
        sitk.ProcessObject.SetGlobalWarningDisplay(warnings_shown)


@contextmanager
def _quiet_nibabel() -> Iterator[None]:
    """Silence nibabel's global logger (it prints the header fixes it makes to stderr)."""
    logger = nib.imageglobals.logger
    disabled, logger.disabled = logger.disabled, True
    try:
        yield
    finally:
        logger.disabled = disabled


def _check_nifti_header(path: Path, nimg: nib.spatialimages.SpatialImage) -> None:
    """Raise ImageGeometryError for a voxel spacing ITK's NIfTI reader would silently change.

    ITK (niftilib) replaces a zero voxel spacing by 1 and a negative one by its absolute
    value; nibabel fixes its copy of the header too. The raw header is read again, unfixed.
    """
    with nimg.file_map["image"].get_prepare_fileobj("rb") as fobj:
        raw = type(nimg.header).from_fileobj(fobj, check=False)
    n_spatial = int(np.clip(raw["dim"][0], 0, 3))
    pixdim = np.asarray(raw["pixdim"][1 : n_spatial + 1], dtype=float)
    if not np.all(np.isfinite(pixdim)) or np.any(pixdim <= 0):
        raise ImageGeometryError(
            f"{str(path)!r}: voxel spacing (pixdim) {tuple(pixdim.tolist())} in the NIfTI "
            "header must be finite and positive (ITK would silently replace it); fix the "
            "header, e.g. with nibabel's header.set_zooms"
        )


def _check_nifti_finite(path: Path, nimg: nib.spatialimages.SpatialImage) -> None:
    """Raise ImageGeometryError for NaN or infinite voxels, which ITK's reader turns into 0.

    Called after ITK has read (and so checked the integrity of) the file.
    """
    if nimg.header.get_data_dtype().kind == "f":
        values = np.asanyarray(nimg.dataobj.get_unscaled())
        check_finite(values.T, repr(str(path)), note=", which ITK would read as 0")


def _read_file(path: Path) -> sitk.Image:
    suffix = _raw_suffix(path)
    if suffix not in READ_SUFFIXES:
        raise _unknown_format(path)
    nimg = None
    if READ_SUFFIXES[suffix] == "NiftiImageIO":
        nimg = _check_nifti_complete(path)
        _check_nifti_header(path, nimg)
        if isinstance(nimg, nib.Nifti2Image):  # ITK 5.4 cannot read NIfTI-2: use nibabel
            return from_nibabel(nimg, str(path))
    reader = sitk.ImageFileReader()
    reader.SetImageIO(READ_SUFFIXES[suffix])
    reader.SetFileName(str(path))
    try:
        with _quiet_stderr():
            image = reader.Execute()
        if nimg is not None:
            _check_nifti_finite(path, nimg)
        return image
    except RuntimeError as exc:
        if "orthonormal" in itk_reason(exc):
            raise ImageGeometryError(
                f"{str(path)!r}: the orientation in the header (sform / qform, or direction "
                "cosines) is singular or not orthonormal, so the voxels have no usable "
                "position; fix the header (e.g. re-export the image from the scanner software)"
            ) from exc
        raise ImageFormatError(
            f"{str(path)!r}: cannot read this {suffix} file, it is corrupt, truncated or not "
            f"a {suffix} image ({itk_reason(exc)})"
        ) from exc


def read_image_header(path: PathLike) -> tuple[tuple[int, ...], tuple[float, ...]]:
    """Size (voxels) and spacing (mm) of an image file, in (x, y, z) order, from its header.

    The voxels are not read nor checked (:func:`read_image` does that): this sizes work
    before it starts, e.g. the memory one image will need.

    Raises
    ------
    InputFileError
        No such file.
    ImageFormatError
        Unknown suffix, or a header that cannot be read.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{str(path)!r}: no such file")
    suffix = _raw_suffix(path)
    if suffix not in READ_SUFFIXES:
        raise _unknown_format(path)
    try:
        if READ_SUFFIXES[suffix] == "NiftiImageIO":  # NIfTI-1 and -2 (ITK reads only -1)
            with _quiet_nibabel():
                header = nib.load(path).header
            size, spacing = header.get_data_shape(), header.get_zooms()
        else:
            reader = sitk.ImageFileReader()
            reader.SetImageIO(READ_SUFFIXES[suffix])
            reader.SetFileName(str(path))
            with _quiet_stderr():
                reader.ReadImageInformation()
            size, spacing = reader.GetSize(), reader.GetSpacing()
    except Exception as exc:  # nibabel and ITK raise many kinds for a corrupt header
        raise ImageFormatError(f"{str(path)!r}: cannot read the {suffix} header ({exc})") from exc
    return tuple(int(n) for n in size[:3]), tuple(float(d) for d in spacing[:3])


def read_image(source: Any, *, series_id: str | None = None, name: str | None = None) -> sitk.Image:
    """Read a 3D image from a file, a DICOM folder, a SimpleITK or a nibabel image.

    Parameters
    ----------
    source : path-like, SimpleITK.Image or nibabel image
        A file ending in one of :data:`IMAGE_SUFFIXES` (``.nii``, ``.nii.gz``, ``.nrrd``,
        ``.nhdr``, ``.mha``, ``.mhd``) or ``.dcm``, a folder holding one DICOM series, a
        SimpleITK image (checked and returned as is, not copied) or a nibabel image
        (``Nifti1Image``, ``Nifti2Image``, any ``SpatialImage``), converted through its
        affine with RAS -> LPS done once (x and y negated).
    series_id : str, optional
        Which DICOM series to read when a folder holds several.
    name : str, optional
        Name to use for ``source`` in error messages (default: the path).

    Returns
    -------
    image : SimpleITK.Image
        3D, scalar, with size, spacing, origin and direction as stored in the file. Its
        array (``sitk.GetArrayViewFromImage``) is indexed ``(z, y, x)``.

    Raises
    ------
    InputFileError
        The file or folder does not exist.
    ImageFormatError
        Unknown suffix; corrupt or truncated file; folder without a DICOM series.
    ImageGeometryError
        Not 3D (2D, 4D), vector/RGB voxels, non-positive spacing, singular or sheared
        direction, non-finite voxels.
    """
    label = describe(source, name)
    if isinstance(source, sitk.Image):
        return check_image(source, name=label)
    if is_nibabel(source):
        return check_image(from_nibabel(source, label), name=label)
    if not isinstance(source, str | os.PathLike):
        raise TypeError(
            "read_image expects a path, a SimpleITK.Image or a nibabel image, got "
            f"{type(source).__name__}"
        )
    path = Path(source)
    if path.is_dir():
        image = read_dicom_folder(path, series_id)
    elif path.is_file():
        image = _read_file(path)
    else:
        raise InputFileError(f"{label!r}: no such file or folder")
    return check_image(image, name=label)


def write_image(
    image: Any,
    path: PathLike,
    *,
    like: Any = None,
    protect: Iterable[PathLike] = (),
    compress: bool = True,
) -> Path:
    """Write a 3D image atomically.

    Parameters
    ----------
    image : SimpleITK.Image or nibabel image
    path : path-like
        Target file; the suffix chooses the format (``.nii``, ``.nii.gz``, ``.nrrd``,
        ``.nhdr``, ``.mha``, ``.mhd``). Written to a temporary file in the same folder, then
        renamed into place (see :func:`atomic_write`).
    like : path-like, SimpleITK.Image or nibabel image, optional
        The input this image was computed for. Its geometry must equal ``image``'s (see
        :func:`check_same_geometry`), else :class:`~medseg.errors.ImageGeometryError`: an
        output label map must sit on its input's grid. A path given here is also protected
        from being overwritten. If ``like`` is a nibabel image and ``path`` is NIfTI, the
        file is written through nibabel in the same NIfTI flavour (1 or 2).
    protect : iterable of path-like
        Input files that must not be overwritten (:class:`~medseg.errors.InputFileError`).
    compress : bool
        Compress NRRD / MetaImage data (lossless). ``.nii.gz`` is always compressed, ``.nii``
        never.

    Returns
    -------
    path : pathlib.Path
    """
    path = Path(path)
    suffix = image_suffix(path)
    if suffix is None:
        raise _unknown_format(path, writing=True)
    protect = list(protect)
    if isinstance(like, str | os.PathLike):
        protect.append(like)
    check_not_protected(path, protect)
    sitk_image = from_nibabel(image, describe(image)) if is_nibabel(image) else image
    if not isinstance(sitk_image, sitk.Image):
        raise TypeError(f"write_image expects a SimpleITK or nibabel image, got {type(image)}")
    if sitk_image.GetDimension() != 3:
        raise ImageGeometryError(
            f"cannot write {str(path)!r}: image is {sitk_image.GetDimension()}D, not 3D"
        )
    if like is not None:
        ref = like if isinstance(like, sitk.Image) else read_image(like)
        problems = check_same_geometry(sitk_image, ref)
        if problems:
            raise ImageGeometryError(
                f"cannot write {str(path)!r}: the image is not on the grid of its input "
                f"{describe(like)}: " + "; ".join(problems)
            )
    nifti = suffix in (".nii", ".nii.gz")
    with atomic_write(path, protect=protect) as tmp:
        if nifti and (is_nibabel(like) or is_nibabel(image)):
            template = like if is_nibabel(like) else image
            nib.save(to_nibabel(sitk_image, like=template), str(tmp))
        else:
            writer = sitk.ImageFileWriter()
            writer.SetImageIO(IMAGE_SUFFIXES[suffix])
            writer.SetFileName(str(tmp))
            writer.SetUseCompression(suffix == ".nii.gz" or (compress and suffix in _COMPRESSIBLE))
            try:
                writer.Execute(sitk_image)
            except RuntimeError as exc:
                raise InputFileError(f"cannot write {str(path)!r}: {itk_reason(exc)}") from exc
    return path
