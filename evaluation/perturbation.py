"""Pose perturbation of test cases: similarity transforms and larger fields of view.

The paper's central claim is pose invariance: the same test case, rotated, scaled or seen in
a larger field of view, should be segmented as well as the original. :func:`random_similarity`
draws a transform of a given size (rotation angle about a random axis, scale growing with
it), :func:`pose_change` builds one of a given rotation and scale, and :func:`perturb_case`
applies it to an image, its label map and its reference landmarks, on the image's own grid
or on a grid padded by a margin: the image is resampled linearly, the label with nearest
neighbour, the landmarks are mapped forward; what lies outside the original image is filled
with a constant, zeros, or noise like the image's border.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation
from sklearn.utils import check_random_state

from medseg.errors import ParameterError
from medseg.io import resample_like, voxel_to_physical

__all__ = [
    "PoseChange",
    "random_similarity",
    "pose_change",
    "perturb_case",
    "padded_grid",
    "FILLS",
    "MAX_ROTATION_DEG",
    "MAX_SCALE",
]

#: Largest rotation of the study (degrees); the scale reaches ``MAX_SCALE`` (or its inverse)
#: at this rotation.
MAX_ROTATION_DEG = 45.0
MAX_SCALE = 1.25
#: What fills the voxels of a perturbed image that lie outside the original: the median of
#: its border voxels, zeros (a scanner's empty field of view), or Gaussian noise with the
#: mean and standard deviation of its border voxels (tissue-like background).
FILLS = ("border", "zeros", "noise")


@dataclass(frozen=True)
class PoseChange:
    """``y = scale * rotation @ (x - centre) + centre`` in physical mm.

    Attributes
    ----------
    rotation : (3, 3) float array
    scale : float
    angle_deg : float
        Rotation angle of ``rotation``.
    """

    rotation: np.ndarray
    scale: float
    angle_deg: float

    def apply(self, points: ArrayLike, centre: ArrayLike) -> np.ndarray:
        """Map ``(N, 3)`` points (mm) about ``centre`` (mm)."""
        points = np.asarray(points, dtype=float)
        centre = np.asarray(centre, dtype=float)
        return self.scale * (points - centre) @ self.rotation.T + centre


def random_similarity(
    angle_deg: float,
    *,
    max_angle_deg: float = MAX_ROTATION_DEG,
    max_scale: float = MAX_SCALE,
    random_state=None,
) -> PoseChange:
    """A rotation of exactly ``angle_deg`` about a uniformly random axis, with a scale.

    Parameters
    ----------
    angle_deg : float
        Size of the perturbation, in ``[0, max_angle_deg]``.
    max_angle_deg : float, default 45
    max_scale : float, default 1.25
        The scale is ``max_scale ** (+-angle_deg / max_angle_deg)`` with a random sign: 1 at
        no rotation, 1.25 or 0.8 at 45 degrees.
    random_state : int, RandomState or None

    Returns
    -------
    PoseChange
    """
    if not 0.0 <= angle_deg <= max_angle_deg:
        raise ParameterError(f"`angle_deg` must be in [0, {max_angle_deg}], got {angle_deg}")
    if max_scale < 1.0:
        raise ParameterError("`max_scale` must be >= 1.")
    rng = check_random_state(random_state)
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    rotation = Rotation.from_rotvec(np.deg2rad(angle_deg) * axis).as_matrix()
    sign = 1.0 if rng.uniform() < 0.5 else -1.0
    scale = float(max_scale ** (sign * angle_deg / max_angle_deg))
    return PoseChange(rotation=rotation, scale=scale, angle_deg=float(angle_deg))


def pose_change(*, angle_deg: float = 0.0, scale: float = 1.0, random_state=None) -> PoseChange:
    """A rotation of ``angle_deg`` (0 to 180) about a uniformly random axis, and a scale.

    For the controlled study: rotation only (``scale=1``), scale only (``angle_deg=0``).
    """
    if not 0.0 <= angle_deg <= 180.0:
        raise ParameterError(f"`angle_deg` must be in [0, 180], got {angle_deg}")
    if not scale > 0:
        raise ParameterError(f"`scale` must be > 0, got {scale}")
    axis = check_random_state(random_state).standard_normal(3)
    axis /= np.linalg.norm(axis)
    rotation = Rotation.from_rotvec(np.deg2rad(angle_deg) * axis).as_matrix()
    return PoseChange(rotation=rotation, scale=float(scale), angle_deg=float(angle_deg))


def _border_values(image: sitk.Image) -> np.ndarray:
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


def perturb_case(
    image: sitk.Image,
    label: sitk.Image,
    landmarks: ArrayLike | None,
    change: PoseChange,
    *,
    centre: ArrayLike | None = None,
    pad_mm: float = 0.0,
    fill: str = "border",
    random_state=None,
) -> tuple[sitk.Image, sitk.Image, np.ndarray | None]:
    """Apply a pose change to a test case, on its own grid or a padded one.

    Parameters
    ----------
    image : 3D SimpleITK image
    label : 3D SimpleITK image
        Label map on ``image``'s grid.
    landmarks : (N, 3) float array, mm, or None
        Reference landmarks, mapped forward.
    change : PoseChange
    centre : (3,) float array, mm, optional
        Fixed point of the transform; default the centroid of the label's foreground, so
        the structure stays in the field of view.
    pad_mm : float, default 0
        Margin added to the grid on every side (:func:`padded_grid`).
    fill : {"border", "zeros", "noise"}, default "border"
        What fills the voxels outside the original image (:data:`FILLS`).
    random_state : int, RandomState or None
        Seeds the noise fill.

    Returns
    -------
    image, label : SimpleITK images
        The input's spacing and direction, on its grid padded by ``pad_mm``; the image
        resampled linearly (float32 unless the fill is a constant), the label with nearest
        neighbour.
    landmarks : (N, 3) float array, mm, or None
    """
    if fill not in FILLS:
        raise ParameterError(f"`fill` must be one of {FILLS}, got {fill!r}")
    if centre is None:
        fg = np.argwhere(sitk.GetArrayViewFromImage(label) > 0)
        if not len(fg):
            fg = np.argwhere(np.ones(sitk.GetArrayViewFromImage(label).shape, dtype=bool))
        centre = voxel_to_physical(label, fg).mean(axis=0)
    centre = np.asarray(centre, dtype=float)
    # Resample pulls output points back into the input: the inverse of the change.
    inverse = sitk.AffineTransform(3)
    inverse.SetMatrix((change.rotation.T / change.scale).ravel().tolist())
    inverse.SetCenter(centre.tolist())
    grid = padded_grid(image, pad_mm) if pad_mm > 0 else image
    border = _border_values(image)
    constant = 0.0 if fill == "zeros" else float(np.median(border))
    moved_image = resample_like(
        image, grid, is_label=False, transform=inverse, default_value=constant
    )
    if fill == "noise":
        ones = sitk.Image(image.GetSize(), sitk.sitkUInt8) + 1
        ones.CopyInformation(image)
        inside = sitk.GetArrayFromImage(resample_like(ones, grid, is_label=True, transform=inverse))
        values = sitk.GetArrayFromImage(sitk.Cast(moved_image, sitk.sitkFloat32))
        rng = check_random_state(random_state)
        outside = inside == 0
        values[outside] = rng.normal(border.mean(), border.std(), size=int(outside.sum()))
        noisy = sitk.GetImageFromArray(values)
        noisy.CopyInformation(grid)
        moved_image = noisy
    moved_label = resample_like(label, grid, is_label=True, transform=inverse)
    moved_landmarks = None if landmarks is None else change.apply(landmarks, centre)
    return moved_image, moved_label, moved_landmarks
