"""Scoring a vertex map against ground-truth correspondences (Kim, Lipman & Funkhouser 2011).

For a map T from A to B and ground-truth rows i (vertex ``A.vts[i]`` of A corresponds to
vertex ``B.vts[i]`` of B), ``err_i = geodesic_B(T(A.vts[i]), B.vts[i]) / sqrt(area(B))``,
with heat-method geodesics on B (:class:`medseg.geometry.GeodesicSolver`). Used by
``benchmarks/bench_matching.py`` and the FAUST test.
"""

from __future__ import annotations

import os

import numpy as np
from numpy.typing import ArrayLike

from medseg.geometry import GeodesicSolver, face_areas

__all__ = ["read_vts", "geodesic_errors"]


def read_vts(path: str | os.PathLike) -> np.ndarray:
    """Ground-truth vertex indices from a ``.vts`` file (one 1-based index a line), 0-based."""
    return np.loadtxt(path, dtype=np.int64) - 1


def geodesic_errors(
    vertices_b: ArrayLike,
    faces_b: ArrayLike,
    truth_b: ArrayLike,
    images: ArrayLike,
    *,
    geodesic: GeodesicSolver | None = None,
) -> np.ndarray:
    """Geodesic distances on B between maps' images and the true vertices, over sqrt(area).

    Parameters
    ----------
    vertices_b : (V_B, 3) float array
    faces_b : (F_B, 3) int array
    truth_b : (R,) int array
        True vertex of B of each row (``B.vts - 1``).
    images : (R,) or (M, R) int array
        Vertex of B to which each of M maps sends the row's vertex of A
        (``forward[A.vts - 1]``).
    geodesic : GeodesicSolver, optional
        A solver on B to reuse; built here if not given.

    Returns
    -------
    errors : float array of the shape of ``images``
        Each row's geodesic error in units of ``sqrt(area(B))``. One distance field is
        solved per distinct true vertex, shared by all maps.
    """
    geo = GeodesicSolver(vertices_b, faces_b) if geodesic is None else geodesic
    scale = np.sqrt(face_areas(vertices_b, faces_b).sum())
    truth = np.asarray(truth_b)
    images = np.asarray(images)
    flat = images.reshape(-1, len(truth))
    errors = np.empty(flat.shape)
    for src in np.unique(truth):
        rows = np.flatnonzero(truth == src)
        errors[:, rows] = geo.distance(src)[flat[:, rows]] / scale
    return errors.reshape(images.shape)
