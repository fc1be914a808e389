"""Resampling: onto another grid, under a similarity, into a larger field of view.

The one place images change grid: :func:`resample_like` (onto a reference's grid; labels by
nearest neighbour or label-linear interpolation, so no label value is invented),
:func:`resample_affine` (moved by an affine map of physical space, onto a grid of choice,
with what lies beyond the original field of view filled by a constant, zeros, or noise like
the image's border),
:func:`padded_grid` (a grid extended by a margin), and :func:`content_mask` (the voxels that
are not such a constant fill). Pose perturbations, the shape's frame and
training-time pose augmentation are all built on these.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation
from sklearn.utils import check_random_state

from medseg.errors import ParameterError

__all__ = [
    "resample_like",
    "resample_affine",
    "padded_grid",
    "content_mask",
    "random_pose",
    "border_values",
    "FILLS",
    "LABEL_INTERPOLATIONS",
]

#: What fills the voxels of a resampled image that lie outside the original: the median of
#: its border voxels, zeros (a scanner's empty field of view), or Gaussian noise with the
#: mean and standard deviation of its border voxels (tissue-like background).
FILLS = ("border", "zeros", "noise")
#: How a label map is interpolated: ``"nearest"`` keeps each output voxel's nearest input
#: label (stair steps of up to half a voxel where the grids do not align); ``"linear"``
#: interpolates every label's indicator linearly and keeps the likeliest label (SimpleITK's
#: label-linear interpolator), which places the boundary between the voxels. Resampled by a
#: random similarity, a hippocampus label map by the two disagrees at a Dice of 0.965.
LABEL_INTERPOLATIONS = {"nearest": sitk.sitkNearestNeighbor, "linear": sitk.sitkLabelLinear}


def resample_like(
    image: sitk.Image,
    reference: sitk.Image,
    *,
    is_label: bool,
    transform: sitk.Transform | None = None,
    default_value: float = 0.0,
    label_interpolation: str = "nearest",
) -> sitk.Image:
    """Resample ``image`` onto the voxel grid of ``reference``.

    Parameters
    ----------
    image : SimpleITK.Image
    reference : SimpleITK.Image
        Supplies the output size, spacing, origin and direction.
    is_label : bool
        A label map (interpolated by ``label_interpolation``: no invented label values) if
        True, an intensity image (linear interpolation) if False.
    transform : SimpleITK.Transform, optional
        Maps points of ``reference``'s space into ``image``'s space; identity by default.
    default_value : float
        Value outside ``image``.
    label_interpolation : {"nearest", "linear"}, default "nearest"
        For a label map (:data:`LABEL_INTERPOLATIONS`).

    Returns
    -------
    resampled : SimpleITK.Image
        ``image``'s pixel type, ``reference``'s geometry exactly.
    """
    if label_interpolation not in LABEL_INTERPOLATIONS:
        raise ParameterError(
            f"`label_interpolation` must be one of {tuple(LABEL_INTERPOLATIONS)}, "
            f"got {label_interpolation!r}"
        )
    interpolator = LABEL_INTERPOLATIONS[label_interpolation] if is_label else sitk.sitkLinear
    return sitk.Resample(
        image,
        reference,
        transform if transform is not None else sitk.Transform(),
        interpolator,
        float(default_value),
        image.GetPixelID(),
    )


def border_values(image: sitk.Image) -> np.ndarray:
    """The voxels on the six faces of an image's grid, as a flat float array.

    What surrounds the field of view: the fill for resampling beyond it (their median) or
    for simulating a larger one (noise with their mean and spread).
    """
    a = sitk.GetArrayViewFromImage(image)
    faces = [a[0], a[-1], a[:, 0], a[:, -1], a[:, :, 0], a[:, :, -1]]
    return np.concatenate([f.ravel() for f in faces]).astype(float)


def padded_grid(image: sitk.Image, margin_mm: float) -> sitk.Image:
    """An empty image on ``image``'s grid extended by ``margin_mm`` on every side.

    Same spacing and direction; the margin is rounded up to whole voxels per axis, so the
    original voxels stay on the new grid.
    """
    if not margin_mm >= 0:
        raise ParameterError(f"`margin_mm` must be >= 0, got {margin_mm}")
    spacing = np.asarray(image.GetSpacing(), dtype=float)
    pad = np.ceil(float(margin_mm) / spacing - 1e-9).astype(int)
    size = np.asarray(image.GetSize()) + 2 * pad
    grid = sitk.Image([int(v) for v in size], sitk.sitkUInt8)
    grid.SetSpacing(image.GetSpacing())
    grid.SetDirection(image.GetDirection())
    grid.SetOrigin(image.TransformContinuousIndexToPhysicalPoint([-float(p) for p in pad]))
    return grid


def content_mask(image: sitk.Image) -> sitk.Image:
    """The voxels of ``image`` that hold the image itself and not a constant padding of its
    field of view, with a margin: uint8 on ``image``'s grid.

    A padding (the ``"zeros"`` and ``"border"`` fills) is a constant region: its value is
    that of the voxels whose 3x3x3 neighbourhood holds one value, and every voxel of that
    value is left out, with the voxels beside one, so that a linear interpolation at a kept
    voxel reads the image alone. Acquired images have noise in every voxel (none of the
    phantom's or the hippocampus crops' voxels is in a constant neighbourhood): all of
    their voxels are kept, found at the cost of one comparison of neighbours. A constant
    region inside the image counts as padding too (CT's air at exactly -1024, an image
    clipped to its range), and a noise-like padding is not told apart, by design.
    """
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise ParameterError("content_mask needs a scalar image")
    values = sitk.GetArrayViewFromImage(image)
    keep = np.ones(values.shape, dtype=np.uint8)
    # a voxel of a constant neighbourhood equals its two neighbours along the last axis
    row = values[..., 1:-1]
    if row.size and np.any((values[..., :-2] == row) & (row == values[..., 2:])):
        flat = _constant_neighbourhoods(values)
        if flat.any():
            fills = values[flat]
            if np.all(fills == fills[0]):  # the usual case: one fill value
                padding = values == fills[0]
            else:
                padding = np.isin(values, np.unique(fills))
            keep[_grown(padding)] = 0  # and the voxels beside it
    mask = sitk.GetImageFromArray(keep)
    mask.CopyInformation(image)
    return mask


def _constant_neighbourhoods(values: np.ndarray) -> np.ndarray:
    """Whether each voxel's 3x3x3 neighbourhood (clipped to the grid) holds one value.

    Axis by axis: a voxel passes an axis when it equals its two neighbours along it and they
    passed the axes before, so the line, then the square, then the cube is constant. The
    same as comparing SciPy's maximum and minimum filters, about ten times faster.
    """
    edge = np.pad(values, 1, mode="edge")  # a clipped neighbourhood: the border repeats
    passed = np.ones(edge.shape, dtype=bool)
    for axis in range(edge.ndim):
        before = [slice(None)] * edge.ndim
        after = [slice(None)] * edge.ndim
        middle = [slice(None)] * edge.ndim
        before[axis], middle[axis], after[axis] = slice(None, -2), slice(1, -1), slice(2, None)
        b, m, a = tuple(before), tuple(middle), tuple(after)
        line = (edge[b] == edge[m]) & (edge[m] == edge[a]) & passed[b] & passed[m] & passed[a]
        passed = np.zeros(edge.shape, dtype=bool)
        passed[m] = line
    return passed[(slice(1, -1),) * edge.ndim]


def _grown(mask: np.ndarray) -> np.ndarray:
    """``mask`` dilated by the 3x3x3 cube (nothing beyond the grid), one axis at a time."""
    grown = mask.copy()
    for axis in range(mask.ndim):
        step = grown.copy()
        lower = [slice(None)] * mask.ndim
        upper = [slice(None)] * mask.ndim
        lower[axis], upper[axis] = slice(None, -1), slice(1, None)
        step[tuple(lower)] |= grown[tuple(upper)]
        step[tuple(upper)] |= grown[tuple(lower)]
        grown = step
    return grown


def resample_affine(
    image: sitk.Image,
    matrix: ArrayLike,
    offset: ArrayLike,
    grid: sitk.Image,
    *,
    is_label: bool = False,
    fill: str = "border",
    random_state=None,
    label_interpolation: str = "nearest",
) -> sitk.Image:
    """``image`` moved by the map ``y = matrix @ x + offset`` (physical mm), on ``grid``.

    Parameters
    ----------
    image : 3D SimpleITK image
    matrix : (3, 3) float array
        Invertible (a similarity: ``scale * rotation``).
    offset : (3,) float array, mm
    grid : 3D SimpleITK image
        The output's size, spacing, origin and direction.
    is_label : bool, default False
        A label map (outside: 0), interpolated by ``label_interpolation``.
    fill : {"border", "zeros", "noise"}, default "border"
        What fills the output voxels whose preimage lies outside ``image`` (:data:`FILLS`);
        ignored for labels.
    random_state : int, RandomState or None
        Seeds the noise fill.
    label_interpolation : {"nearest", "linear"}, default "nearest"
        For a label map (:data:`LABEL_INTERPOLATIONS`).

    Returns
    -------
    SimpleITK image
        float32 for an image (the input's type when the fill is a constant), the input's
        type for a label map.
    """
    if fill not in FILLS:
        raise ParameterError(f"`fill` must be one of {FILLS}, got {fill!r}")
    matrix = np.asarray(matrix, dtype=float)
    offset = np.asarray(offset, dtype=float)
    inverse = np.linalg.inv(matrix)
    transform = sitk.AffineTransform(3)  # resampling pulls output points back: the inverse
    transform.SetMatrix(inverse.ravel().tolist())
    transform.SetTranslation((-(inverse @ offset)).tolist())
    if is_label:
        return resample_like(
            image, grid, is_label=True, transform=transform, label_interpolation=label_interpolation
        )
    border = border_values(image)
    constant = 0.0 if fill == "zeros" else float(np.median(border))
    moved = resample_like(image, grid, is_label=False, transform=transform, default_value=constant)
    if fill != "noise":
        return moved
    ones = sitk.Image(image.GetSize(), sitk.sitkUInt8) + 1
    ones.CopyInformation(image)
    outside = sitk.GetArrayFromImage(resample_like(ones, grid, is_label=True, transform=transform))
    outside = outside == 0
    values = sitk.GetArrayFromImage(sitk.Cast(moved, sitk.sitkFloat32))
    rng = check_random_state(random_state)
    values[outside] = rng.normal(border.mean(), border.std(), size=int(outside.sum()))
    noisy = sitk.GetImageFromArray(values)
    noisy.CopyInformation(grid)
    return noisy


def random_pose(
    image: sitk.Image,
    centre: ArrayLike,
    *,
    max_angle_deg: float,
    scale_range: tuple[float, float],
    pad_mm: float,
    random_state=None,
) -> tuple[sitk.Image, np.ndarray, float, np.ndarray]:
    """A copy of ``image`` in a random pose, size and field of view (training augmentation).

    A rotation by an angle uniform in ``[0, max_angle_deg]`` about a uniformly random axis
    and a scale log-uniform in ``scale_range``, about ``centre`` (mm); resampled linearly
    onto the image's grid padded by ``pad_mm``, filled with zeros, noise like the image's
    border, or its border median (:data:`FILLS`, one at random). A model trained on such
    copies sees the anatomy in poses, sizes, interpolations and surroundings the training
    crops never show.

    Returns
    -------
    image : SimpleITK image
        The copy.
    rotation : (3, 3) float array
    scale : float
    offset : (3,) float array, mm
        The map of the input's mm onto the copy's: ``y = scale * rotation @ x + offset``.
    """
    rng = check_random_state(random_state)
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    angle = np.deg2rad(rng.uniform(0.0, float(max_angle_deg)))
    low, high = (float(v) for v in scale_range)
    scale = float(np.exp(rng.uniform(np.log(low), np.log(high))))
    rotation = Rotation.from_rotvec(angle * axis).as_matrix()
    centre = np.asarray(centre, dtype=float)
    offset = centre - scale * rotation @ centre
    fill = FILLS[int(rng.randint(len(FILLS)))]
    grid = padded_grid(image, float(pad_mm))
    moved = resample_affine(image, scale * rotation, offset, grid, fill=fill, random_state=rng)
    return moved, rotation, scale, offset
