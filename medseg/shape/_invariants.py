"""Pose-invariant descriptors of a triangle of landmarks.

All are computed from the three side lengths only, so they are unchanged by any rotation,
reflection and translation of the triangle; relative distances and angles are also unchanged
by uniform scaling (similarity invariants), relative distances with size are not. All are
finite for every triangle, degenerate ones included (collinear or coincident vertices).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from medseg.errors import ParameterError

__all__ = ["relative_distances", "relative_distances_and_size", "triangle_angles", "INVARIANTS"]

# Side lengths below this (relative to the perimeter, or absolute in mm for a zero perimeter)
# are treated as zero; it keeps degenerate triangles finite without biasing normal ones.
_TINY = 1e-12


def _sides(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``d_ij, d_jk, d_ki`` of triangles ``points[..., (i, j, k), :]``."""
    pi, pj, pk = points[..., 0, :], points[..., 1, :], points[..., 2, :]
    d_ij = np.sqrt(((pi - pj) ** 2).sum(-1))
    d_jk = np.sqrt(((pj - pk) ** 2).sum(-1))
    d_ki = np.sqrt(((pk - pi) ** 2).sum(-1))
    return d_ij, d_jk, d_ki


def _check_triangles(points: ArrayLike) -> np.ndarray:
    pts = np.asarray(points, dtype=float)
    if pts.ndim < 2 or pts.shape[-2:] != (3, 3):
        raise ParameterError(
            f"`points` must have shape (..., 3, 3) (triangle vertices i, j, k in x, y, z); "
            f"got {pts.shape}"
        )
    return pts


def relative_distances_from_sides(d_ij, d_jk, d_ki) -> np.ndarray:
    """Relative distances from side lengths; see :func:`relative_distances`.

    Parameters
    ----------
    d_ij, d_jk, d_ki : broadcastable float arrays, mm

    Returns
    -------
    (..., 2) float array
    """
    perimeter = d_ij + d_jk + d_ki
    inv = 1.0 / np.maximum(perimeter, _TINY)
    return np.stack(np.broadcast_arrays(d_ij * inv, d_jk * inv), axis=-1)


def relative_distances_and_size_from_sides(d_ij, d_jk, d_ki) -> np.ndarray:
    """Relative distances and the log perimeter; see :func:`relative_distances_and_size`."""
    perimeter = np.maximum(d_ij + d_jk + d_ki, _TINY)
    rel = relative_distances_from_sides(d_ij, d_jk, d_ki)
    size = np.broadcast_to(np.log(perimeter), rel.shape[:-1])
    return np.concatenate([rel, size[..., None]], axis=-1)


def triangle_angles_from_sides(d_ij, d_jk, d_ki) -> np.ndarray:
    """Interior angles at vertices i and j from side lengths; see :func:`triangle_angles`."""
    d_ij, d_jk, d_ki = np.broadcast_arrays(d_ij, d_jk, d_ki)
    # law of cosines; a zero adjacent side makes the angle undefined: cos = 0 (right angle)
    # by convention, which keeps the value finite and the function symmetric.
    num_i = d_ij**2 + d_ki**2 - d_jk**2
    den_i = 2.0 * d_ij * d_ki
    num_j = d_ij**2 + d_jk**2 - d_ki**2
    den_j = 2.0 * d_ij * d_jk
    cos_i = np.where(den_i > _TINY, num_i / np.maximum(den_i, _TINY), 0.0)
    cos_j = np.where(den_j > _TINY, num_j / np.maximum(den_j, _TINY), 0.0)
    return np.stack([np.arccos(np.clip(cos_i, -1, 1)), np.arccos(np.clip(cos_j, -1, 1))], -1)


def relative_distances(points: ArrayLike) -> np.ndarray:
    """Relative side lengths of triangles, the invariant of Wang et al. (2010).

    For a clique ``c = (i, j, k)`` with ``i < j < k``,
    ``d_c = (d_ij, d_jk) / (d_ij + d_jk + d_ki)``.

    Parameters
    ----------
    points : (..., 3, 3) float array, mm
        Vertices i, j, k of each triangle (second-to-last axis), in (x, y, z).

    Returns
    -------
    (..., 2) float array
        Both values lie in [0, 1/2]. A triangle whose three vertices coincide (perimeter 0)
        gives (0, 0).

    Notes
    -----
    Unchanged by rotation, reflection, translation and uniform scaling.

    References
    ----------
    .. [1] C. Wang, O. Teboul, F. Michel, S. Essafi, N. Paragios, "3D knowledge-based
       segmentation using pose-invariant higher-order graphs", MICCAI 2010.
       :doi:`10.1007/978-3-642-15711-0_24`
    """
    return relative_distances_from_sides(*_sides(_check_triangles(points)))


def relative_distances_and_size(points: ArrayLike) -> np.ndarray:
    """Relative side lengths of triangles and their size, ``(d_c, log(perimeter / 1 mm))``.

    The paper's invariant :func:`relative_distances` is blind to scale, so on its own any
    triangle of the right shape matches, however large; with few detector candidates most
    of the ``L^3`` candidate triples of a clique contain such a look-alike, and the triplet
    MRF's relaxation becomes loose (measured on the phantom: median landmark error 10.9 mm
    with the paper's invariant, 4.7 mm with this one, the same candidates and solver). The
    log perimeter adds the size of the triangle, whose density is learned from the
    training population: the descriptor is still unchanged by rotation, reflection and
    translation, and accepts the scales seen in training (a child's organ in a model
    trained on adults is out of its range).

    Parameters
    ----------
    points : (..., 3, 3) float array, mm
        Vertices i, j, k of each triangle, in (x, y, z).

    Returns
    -------
    (..., 3) float array
        ``d_ij / p``, ``d_jk / p`` and ``log p`` with ``p`` the perimeter in mm.
    """
    return relative_distances_and_size_from_sides(*_sides(_check_triangles(points)))


def triangle_angles(points: ArrayLike) -> np.ndarray:
    """Interior angles at vertices i and j of triangles (the third is pi minus their sum).

    Parameters
    ----------
    points : (..., 3, 3) float array, mm
        Vertices i, j, k of each triangle, in (x, y, z).

    Returns
    -------
    (..., 2) float array, radians, in [0, pi]
        Angles at i (between edges i-j and i-k) and at j. When an edge adjacent to a vertex
        has zero length the angle there is undefined and reported as pi/2.

    Notes
    -----
    Unchanged by rotation, reflection, translation and uniform scaling.
    """
    return triangle_angles_from_sides(*_sides(_check_triangles(points)))


# name -> function of the three side lengths
INVARIANTS = {
    "distance": relative_distances_from_sides,
    "distance_size": relative_distances_and_size_from_sides,
    "angle": triangle_angles_from_sides,
}
