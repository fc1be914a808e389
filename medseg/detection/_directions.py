"""Image gradient directions at physical points, for the reflection-sensitive prior term.

The direction of the smoothed intensity gradient at a boundary point is the boundary's normal
up to the sign of the local contrast. It turns with the image under any rotation, so quantities
built from it and from the landmarks (:class:`medseg.shape.OrientationPrior`) are pose
invariant, but a mirror image reverses their handedness.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from numpy.typing import ArrayLike
from scipy import ndimage

from medseg.errors import MedsegError, ParameterError
from medseg.io import physical_to_voxel

__all__ = ["gradient_directions"]


def gradient_directions(
    image: sitk.Image, points: ArrayLike, *, sigma_mm: float = 1.0
) -> np.ndarray:
    """Unit gradient of the Gaussian-smoothed image at physical points.

    Parameters
    ----------
    image : 3D SimpleITK image
    points : (M, 3) float array, mm
        Physical (x, y, z) positions; outside the image the nearest voxel's gradient is used.
    sigma_mm : float, mm
        Standard deviation of the Gaussian smoothing before the central differences, in mm
        (converted per axis, so anisotropic spacing is handled).

    Returns
    -------
    (M, 3) float array
        Unit vectors in physical (x, y, z) coordinates (the image direction is applied);
        zero where the gradient vanishes (a constant image).
    """
    if image.GetDimension() != 3:
        raise MedsegError(f"gradient_directions needs a 3D image, got {image.GetDimension()}D")
    if not float(sigma_mm) > 0:
        raise ParameterError(f"`sigma_mm` must be > 0, got {sigma_mm}")
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    spacing_zyx = np.asarray(image.GetSpacing(), dtype=float)[::-1]
    # scipy rather than SimpleITK's recursive Gaussian, which refuses axes under 4 voxels
    smooth = ndimage.gaussian_filter(
        sitk.GetArrayFromImage(image).astype(np.float32),
        sigma=float(sigma_mm) / spacing_zyx,
        mode="nearest",
    )
    zyx = physical_to_voxel(image, pts).T
    index_gradient = np.zeros((len(pts), 3))  # d/d(index axis), per mm, in (x, y, z) order
    for axis in range(3):
        if smooth.shape[axis] < 2:
            continue  # no extent along this axis: no gradient along it
        g = np.gradient(smooth, spacing_zyx[axis], axis=axis)
        index_gradient[:, 2 - axis] = ndimage.map_coordinates(g, zyx, order=1, mode="nearest")
    direction = np.asarray(image.GetDirection(), dtype=float).reshape(3, 3)
    out = index_gradient @ direction.T  # the index axes' directions in physical space
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, norm, out=np.zeros_like(out), where=norm > 1e-12)
