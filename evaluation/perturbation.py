"""Pose perturbation of test cases: random similarity transforms of a given size.

The paper's central claim is pose invariance: the same test case, rotated and scaled, should
be segmented as well as the original. :func:`random_similarity` draws a transform of a
given size (rotation angle about a random axis, scale growing with it), and
:func:`perturb_case` applies it to an image, its label map and its reference landmarks, on
the image's own grid: the image is resampled linearly, the label with nearest neighbour, the
landmarks are mapped forward.
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

__all__ = ["PoseChange", "random_similarity", "perturb_case", "MAX_ROTATION_DEG", "MAX_SCALE"]

#: Largest rotation of the study (degrees); the scale reaches ``MAX_SCALE`` (or its inverse)
#: at this rotation.
MAX_ROTATION_DEG = 45.0
MAX_SCALE = 1.25


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


def _border_median(image: sitk.Image) -> float:
    a = sitk.GetArrayViewFromImage(image)
    faces = [a[0], a[-1], a[:, 0], a[:, -1], a[:, :, 0], a[:, :, -1]]
    return float(np.median(np.concatenate([f.ravel() for f in faces])))


def perturb_case(
    image: sitk.Image,
    label: sitk.Image,
    landmarks: ArrayLike | None,
    change: PoseChange,
    *,
    centre: ArrayLike | None = None,
) -> tuple[sitk.Image, sitk.Image, np.ndarray | None]:
    """Apply a pose change to a test case, on its own grid.

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

    Returns
    -------
    image, label : SimpleITK images
        Same size, spacing, origin and direction as the inputs; the image resampled
        linearly (outside: the median of the border voxels), the label with nearest
        neighbour.
    landmarks : (N, 3) float array, mm, or None
    """
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
    moved_image = resample_like(
        image, image, is_label=False, transform=inverse, default_value=_border_median(image)
    )
    moved_label = resample_like(label, label, is_label=True, transform=inverse)
    moved_landmarks = None if landmarks is None else change.apply(landmarks, centre)
    return moved_image, moved_label, moved_landmarks
