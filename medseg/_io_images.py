"""Read, check, convert and write 3D images (SimpleITK inside, nibabel accepted and returned)."""

from __future__ import annotations

import gzip
import os
import secrets
import shutil
import time
import zlib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import nibabel as nib
import numpy as np
import SimpleITK as sitk

from medseg._io_atomic import PathLike, atomic_write, check_not_protected
from medseg.errors import ImageFormatError, ImageGeometryError, InputFileError, LabelError

__all__ = [
    "IMAGE_SUFFIXES",
    "image_suffix",
    "read_image",
    "read_label",
    "select_labels",
    "resample_like",
    "to_nibabel",
    "as_input_type",
    "write_image",
    "write_dicom_series",
    "check_image",
    "check_same_geometry",
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
_READ_SUFFIXES = {**IMAGE_SUFFIXES, ".dcm": "GDCMImageIO"}
_COMPRESSIBLE = (".nrrd", ".nhdr", ".mha", ".mhd")

# nibabel affines map to RAS+ world coordinates, ITK to LPS: flip x and y, once, here.
_RAS_LPS = np.diag([-1.0, -1.0, 1.0])

_INTEGER_PIXELS = {
    sitk.sitkUInt8,
    sitk.sitkInt8,
    sitk.sitkUInt16,
    sitk.sitkInt16,
    sitk.sitkUInt32,
    sitk.sitkInt32,
    sitk.sitkUInt64,
    sitk.sitkInt64,
}
_FLOAT_PIXELS = {sitk.sitkFloat32, sitk.sitkFloat64}

# --------------------------------------------------------------------------- helpers


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
    for suffix in _READ_SUFFIXES:
        if name.endswith(suffix):
            return suffix
    return "".join(Path(name).suffixes[-2:]) if name.endswith(".gz") else Path(name).suffix


def _unknown_format(path: PathLike, *, writing: bool = False) -> ImageFormatError:
    suffix = _raw_suffix(path)
    supported = tuple(IMAGE_SUFFIXES) if writing else (*_READ_SUFFIXES, "a DICOM folder")
    return ImageFormatError(
        f"{str(path)!r}: unknown image format {suffix or '(no suffix)'!r}; "
        f"supported{' for writing' if writing else ''}: {', '.join(supported)}"
    )


def _describe(source: Any, name: str | None = None) -> str:
    """A name for ``source`` to use in error messages."""
    if name:
        return str(name)
    if isinstance(source, str | os.PathLike):
        return str(source)
    if isinstance(source, nib.spatialimages.SpatialImage):
        filename = source.get_filename()
        return filename if filename else f"the given nibabel {type(source).__name__}"
    return "the given SimpleITK image"


def _is_nibabel(obj: Any) -> bool:
    return isinstance(obj, nib.spatialimages.SpatialImage)


def _check_direction(direction: np.ndarray, name: str) -> None:
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
        or voxels.
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
    _check_direction(np.asarray(image.GetDirection(), dtype=float).reshape(3, 3), name)
    if image.GetPixelID() in _FLOAT_PIXELS:
        values = sitk.GetArrayViewFromImage(image)
        finite = np.isfinite(values)
        if not finite.all():
            n_bad = int(finite.size - np.count_nonzero(finite))
            first = tuple(int(i) for i in np.argwhere(~finite)[0])
            raise ImageGeometryError(
                f"{name}: {n_bad} voxel(s) are NaN or infinite (first at (z, y, x) = {first}); "
                "replace them (e.g. with 0) before using the image"
            )
    return image


# --------------------------------------------------------------------------- nibabel


def _from_nibabel(img: nib.spatialimages.SpatialImage, name: str) -> sitk.Image:
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
    _check_direction(direction, name)
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
    if _is_nibabel(like):
        return to_nibabel(image, like=like)
    return image


# --------------------------------------------------------------------------- reading


def _check_nifti_complete(path: Path) -> nib.spatialimages.SpatialImage:
    """Raise ImageFormatError if a NIfTI file's header is unreadable or its data truncated.

    ITK reads a truncated NIfTI file without complaint (the missing voxels come back as
    garbage), so the byte count is checked here against the header. Returns the (lazily
    loaded) nibabel image.
    """
    try:
        nimg = nib.load(path)
        header = nimg.header
        shape = header.get_data_shape()
        # nibabel resets the header's vox_offset after loading; the proxy keeps the real one
        offset = int(getattr(nimg.dataobj, "offset", header.get_data_offset()))
        need = offset + int(np.prod(shape)) * header.get_data_dtype().itemsize
    except Exception as exc:  # nibabel raises many types for a bad header
        raise ImageFormatError(
            f"{str(path)!r}: not a readable NIfTI file (corrupt or truncated header: {exc})"
        ) from exc
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


def _read_dicom_folder(folder: Path, series_id: str | None) -> sitk.Image:
    try:
        ids = sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(folder))
    except RuntimeError as exc:
        raise ImageFormatError(f"{str(folder)!r}: cannot scan for DICOM files: {exc}") from exc
    if not ids:
        raise ImageFormatError(
            f"{str(folder)!r}: folder holds no DICOM series; give an image file "
            f"({', '.join(_READ_SUFFIXES)}) or a folder of DICOM slices"
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
            f"{str(folder)!r}: DICOM series {series_id!r} is unreadable: {_itk_reason(exc)}"
        ) from exc


def _itk_reason(exc: RuntimeError) -> str:
    """The informative last line of a SimpleITK exception (no C++ file paths)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return lines[-1] if lines else "unknown error"


def _read_file(path: Path) -> sitk.Image:
    suffix = _raw_suffix(path)
    if suffix not in _READ_SUFFIXES:
        raise _unknown_format(path)
    if _READ_SUFFIXES[suffix] == "NiftiImageIO":
        nimg = _check_nifti_complete(path)
        if isinstance(nimg, nib.Nifti2Image):  # ITK 5.4 cannot read NIfTI-2: use nibabel
            return _from_nibabel(nimg, str(path))
    reader = sitk.ImageFileReader()
    reader.SetImageIO(_READ_SUFFIXES[suffix])
    reader.SetFileName(str(path))
    try:
        return reader.Execute()
    except RuntimeError as exc:
        raise ImageFormatError(
            f"{str(path)!r}: cannot read this {suffix} file, it is corrupt, truncated or not "
            f"a {suffix} image ({_itk_reason(exc)})"
        ) from exc


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
    label = _describe(source, name)
    if isinstance(source, sitk.Image):
        return check_image(source, name=label)
    if _is_nibabel(source):
        return check_image(_from_nibabel(source, label), name=label)
    if not isinstance(source, str | os.PathLike):
        raise TypeError(
            "read_image expects a path, a SimpleITK.Image or a nibabel image, got "
            f"{type(source).__name__}"
        )
    path = Path(source)
    if path.is_dir():
        image = _read_dicom_folder(path, series_id)
    elif path.is_file():
        image = _read_file(path)
    else:
        raise InputFileError(f"{label!r}: no such file or folder")
    return check_image(image, name=label)


# --------------------------------------------------------------------------- labels


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
    label_name = _describe(source, name)
    label = read_image(source, name=label_name)
    values = sitk.GetArrayViewFromImage(label)
    if label.GetPixelID() not in _INTEGER_PIXELS:
        if not np.array_equal(values, np.round(values)):
            raise LabelError(
                f"{label_name}: label map has non-integral values "
                f"({label.GetPixelIDTypeAsString()}); is this an intensity image, or was it "
                "resampled with linear interpolation? Use nearest neighbour for labels"
            )
    low, high = (values.min(), values.max()) if values.size else (0, 0)
    if low < 0:
        raise LabelError(f"{label_name}: label map has negative values (min {low})")
    if label.GetPixelID() not in _INTEGER_PIXELS:
        target = next(
            pid
            for pid, dtype in (
                (sitk.sitkUInt8, np.uint8),
                (sitk.sitkUInt16, np.uint16),
                (sitk.sitkUInt32, np.uint32),
                (sitk.sitkUInt64, np.uint64),
            )
            if high <= np.iinfo(dtype).max
        )
        label = sitk.Cast(label, target)
    if reference is not None:
        ref_name = _describe(reference)
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
        label_name = _describe(label_image, name)
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


def resample_like(
    image: sitk.Image,
    reference: sitk.Image,
    *,
    is_label: bool,
    transform: sitk.Transform | None = None,
    default_value: float = 0.0,
) -> sitk.Image:
    """Resample ``image`` onto the voxel grid of ``reference``.

    Parameters
    ----------
    image : SimpleITK.Image
    reference : SimpleITK.Image
        Supplies the output size, spacing, origin and direction.
    is_label : bool
        Nearest-neighbour interpolation (no invented label values) if True, linear if False.
    transform : SimpleITK.Transform, optional
        Maps points of ``reference``'s space into ``image``'s space; identity by default.
    default_value : float
        Value outside ``image``.

    Returns
    -------
    resampled : SimpleITK.Image
        ``image``'s pixel type, ``reference``'s geometry exactly.
    """
    interpolator = sitk.sitkNearestNeighbor if is_label else sitk.sitkLinear
    return sitk.Resample(
        image,
        reference,
        transform if transform is not None else sitk.Transform(),
        interpolator,
        float(default_value),
        image.GetPixelID(),
    )


# --------------------------------------------------------------------------- writing


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
    sitk_image = _from_nibabel(image, _describe(image)) if _is_nibabel(image) else image
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
                f"{_describe(like)}: " + "; ".join(problems)
            )
    nifti = suffix in (".nii", ".nii.gz")
    with atomic_write(path, protect=protect) as tmp:
        if nifti and (_is_nibabel(like) or _is_nibabel(image)):
            template = like if _is_nibabel(like) else image
            nib.save(to_nibabel(sitk_image, like=template), str(tmp))
        else:
            writer = sitk.ImageFileWriter()
            writer.SetImageIO(IMAGE_SUFFIXES[suffix])
            writer.SetFileName(str(tmp))
            writer.SetUseCompression(suffix == ".nii.gz" or (compress and suffix in _COMPRESSIBLE))
            try:
                writer.Execute(sitk_image)
            except RuntimeError as exc:
                raise InputFileError(f"cannot write {str(path)!r}: {_itk_reason(exc)}") from exc
    return path


# --------------------------------------------------------------------------- DICOM

_DICOM_PIXELS = {sitk.sitkUInt8, sitk.sitkInt8, sitk.sitkUInt16, sitk.sitkInt16}


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
    image = read_image(image)
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
                    f"cannot write DICOM series {str(folder)!r}: {_itk_reason(exc)}"
                ) from exc
        if folder.is_dir():
            folder.rmdir()  # empty, checked above
        os.replace(tmp, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder
