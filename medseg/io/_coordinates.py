"""Array indices <-> physical points, the one conversion between the two conventions.

Voxel arrays are SimpleITK's ``(z, y, x)`` numpy views; points are ``(N, 3)`` millimetres,
``(x, y, z)``, in the image's world frame (ITK / LPS). Spacing and direction cosines
(anisotropic, oblique) come from the image, never by hand.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from numpy.typing import ArrayLike

__all__ = ["voxel_to_physical", "physical_to_voxel", "image_geometry"]


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
