"""Figures medseg can write: a slice of an image next to, and overlaid with, its label.

Rendering uses matplotlib's Agg backend (no display needed) and the file is written
atomically. ``python -m medseg.evaluation.phantom_figure docs/phantom.png`` draws a few
subjects of the synthetic phantom cohort with :func:`save_cohort_png`.
"""

from __future__ import annotations

import io as _bytes_io
import os
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from medseg.errors import ImageGeometryError, InputFileError, MedsegError, ParameterError
from medseg.io import atomic_write, physical_to_voxel, read_image, read_label

__all__ = ["plot_slice", "save_slice_png", "save_cohort_png"]

_AXIS_NAMES = {0: "z", 1: "y", 2: "x"}


def _read(source, *, kind: str) -> sitk.Image:
    if isinstance(source, sitk.Image):
        return source
    return read_label(source) if kind == "label" else read_image(source)


def _slice_arrays(
    image: sitk.Image, label: sitk.Image | None, axis: int, index: int | None
) -> tuple[np.ndarray, np.ndarray | None, int, float]:
    """2D image and label slices (rows, cols), the slice index and the pixel aspect ratio."""
    if image.GetDimension() != 3:
        raise ImageGeometryError(f"save_slice_png needs a 3D image, got {image.GetDimension()}D")
    if axis not in _AXIS_NAMES:
        raise ParameterError(
            f"`axis` must be 0 (z), 1 (y) or 2 (x) of the (z, y, x) array, not {axis}"
        )
    array = sitk.GetArrayViewFromImage(image)
    lab = None
    if label is not None:
        if label.GetSize() != image.GetSize():
            raise ImageGeometryError(
                f"label size {label.GetSize()} differs from image size {image.GetSize()}: "
                "pass the label map that belongs to this image"
            )
        lab = sitk.GetArrayViewFromImage(label)
    if index is None:
        if lab is not None and np.any(lab):
            # The slice with the largest labelled area.
            other = tuple(a for a in range(3) if a != axis)
            index = int(np.argmax(np.count_nonzero(lab, axis=other)))
        else:
            index = array.shape[axis] // 2
    if not 0 <= index < array.shape[axis]:
        raise ParameterError(
            f"`index` {index} is outside 0..{array.shape[axis] - 1} along axis {axis}"
        )
    image2d = np.take(array, index, axis=axis)
    label2d = None if lab is None else np.take(lab, index, axis=axis)
    spacing_zyx = np.asarray(image.GetSpacing())[::-1]
    rows, cols = [a for a in range(3) if a != axis]
    return image2d, label2d, index, float(spacing_zyx[rows] / spacing_zyx[cols])


def _points_near_slice(image: sitk.Image, points, axis: int, index: int) -> np.ndarray | None:
    """(K, 2) in-slice (row, col) indices of the points within 1 voxel of the slice."""
    if points is None:
        return None
    zyx = physical_to_voxel(image, np.asarray(points, dtype=float).reshape(-1, 3))
    near = np.abs(zyx[:, axis] - index) <= 1.0
    return zyx[near][:, [a for a in range(3) if a != axis]]


def _draw(axes_row, image2d, label2d, aspect: float, title: str, points2d=None) -> None:
    from matplotlib.colors import ListedColormap

    lo, hi = np.percentile(image2d, [1, 99.5])
    show = {"cmap": "gray", "vmin": lo, "vmax": hi, "aspect": aspect, "origin": "lower"}
    axes_row[0].imshow(image2d, interpolation="nearest", **show)
    axes_row[0].set_title(title, fontsize=8)
    if label2d is not None:
        colours = ListedColormap(["black", "tab:orange", "tab:cyan", "tab:green", "tab:pink"])
        axes_row[1].imshow(
            np.clip(label2d, 0, 4),
            cmap=colours,
            vmin=0,
            vmax=4,
            aspect=aspect,
            origin="lower",
            interpolation="nearest",
        )
        axes_row[1].set_title("label", fontsize=8)
        axes_row[2].imshow(image2d, interpolation="nearest", **show)
        for value in np.unique(label2d[label2d > 0]):
            axes_row[2].contour(
                label2d == value,
                levels=[0.5],
                colors=[colours(int(min(value, 4)))],
                linewidths=0.8,
            )
        axes_row[2].set_title("overlay", fontsize=8)
    if points2d is not None and len(points2d):
        axes_row[-1].plot(
            points2d[:, 1], points2d[:, 0], "o", ms=3, mfc="none", mec="tab:red", mew=0.8
        )
        axes_row[-1].set_xlim(-0.5, image2d.shape[1] - 0.5)
        axes_row[-1].set_ylim(-0.5, image2d.shape[0] - 0.5)
    for ax in axes_row:
        ax.set_xticks([])
        ax.set_yticks([])


def _save_figure(fig, path: Path, dpi: int) -> Path:
    path = Path(path)
    if not path.parent.is_dir():
        raise InputFileError(f"cannot write {path}: folder {path.parent} does not exist")
    buffer = _bytes_io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, bbox_inches="tight")
    with atomic_write(path) as tmp:
        Path(tmp).write_bytes(buffer.getvalue())
    return path


def save_slice_png(
    image,
    label,
    path: str | os.PathLike,
    *,
    axis: int = 0,
    index: int | None = None,
    landmarks=None,
    dpi: int = 110,
) -> Path:
    """Write one slice of an image next to its label and overlaid with it, as a PNG.

    Parameters
    ----------
    image : sitk.Image, nibabel image or path
        3D image.
    label : sitk.Image, nibabel image, path or None
        Label map on the image's grid; ``None`` draws the image alone.
    path : path-like
        Output ``.png``; written atomically (temporary file, then rename).
    axis : {0, 1, 2}, default 0
        Axis of the SimpleITK ``(z, y, x)`` array to cut across: 0 gives a slice of constant
        z index. Pixels are drawn with the physical aspect ratio of the spacing.
    index : int, optional
        Slice index along ``axis``. Default: the slice with the largest labelled area, or
        the middle slice without a label.
    landmarks : (N, 3) float array, mm (x, y, z), optional
        Points drawn as red circles on the last panel when within one voxel of the slice.
    dpi : int, default 110

    Returns
    -------
    path : Path
        The written file.
    """
    return _save_figure(
        plot_slice(image, label, axis=axis, index=index, landmarks=landmarks), path, dpi
    )


def plot_slice(image, label=None, *, axis: int = 0, index: int | None = None, landmarks=None):
    """The figure of :func:`save_slice_png`, returned instead of written (for notebooks).

    Returns
    -------
    figure : matplotlib.figure.Figure
        Image, label and overlay panels (the image alone when ``label`` is None).
    """
    from matplotlib.figure import Figure

    image = _read(image, kind="image")
    label = None if label is None else _read(label, kind="label")
    image2d, label2d, index, aspect = _slice_arrays(image, label, axis, index)
    n_panels = 1 if label2d is None else 3
    fig = Figure(figsize=(2.4 * n_panels, 2.6))
    axes = fig.subplots(1, n_panels, squeeze=False)[0]
    points2d = _points_near_slice(image, landmarks, axis, index)
    _draw(axes, image2d, label2d, aspect, f"image, {_AXIS_NAMES[axis]} index {index}", points2d)
    return fig


def save_cohort_png(
    cohort, path: str | os.PathLike, *, n_cases: int = 3, axis: int = 0, dpi: int = 90
) -> Path:
    """Write a grid of the first ``n_cases`` cases: image, label and overlay per row.

    Landmarks of a case (``case.landmarks``) within one voxel of the slice are drawn as red
    circles on the overlay.

    Parameters
    ----------
    cohort : Cohort
        From :func:`medseg.datasets.load_cohort` or :func:`medseg.datasets.make_phantom_cohort`.
    path : path-like
        Output ``.png``; written atomically.
    n_cases : int, default 3
    axis : {0, 1, 2}, default 0
        See :func:`save_slice_png`.
    dpi : int, default 90

    Returns
    -------
    path : Path
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    cases = list(cohort)[:n_cases]
    if not cases:
        raise MedsegError("save_cohort_png: the cohort has no cases to draw")
    fig = Figure(figsize=(7.2, 2.5 * len(cases)))
    grid = fig.subplots(len(cases), 3, squeeze=False)
    for row, case in zip(grid, cases, strict=True):
        image = case.load_image()
        label = case.load_label()
        image2d, label2d, index, aspect = _slice_arrays(image, label, axis, None)
        points2d = _points_near_slice(image, case.load_landmarks(), axis, index)
        title = f"{case.case_id}, {_AXIS_NAMES[axis]} = {index}"
        _draw(row, image2d, label2d, aspect, title, points2d)
    return _save_figure(fig, path, dpi)
