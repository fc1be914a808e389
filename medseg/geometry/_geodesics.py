"""Geodesic distances and log maps on a triangle mesh (potpourri3d), factorised once."""

from __future__ import annotations

import numpy as np
import potpourri3d as pp3d
from numpy.typing import ArrayLike

__all__ = ["GeodesicSolver"]


class GeodesicSolver:
    """Geodesic distances on a mesh by the heat method (potpourri3d), factorised once.

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (F, 3) int array

    References
    ----------
    .. [1] Crane, K., Weischedel, C. & Wardetzky, M. "Geodesics in heat." ACM TOG 32(5),
       2013. doi:10.1145/2516971.2516977
    """

    def __init__(self, vertices: ArrayLike, faces: ArrayLike):
        self._vertices = np.asarray(vertices, float)
        self._faces = np.asarray(faces, np.int64)
        self._solver = pp3d.MeshHeatMethodDistanceSolver(self._vertices, self._faces)
        self._vector_solver = None

    def log_map(self, source: int) -> np.ndarray:
        """Logarithmic map at vertex ``source`` (vector heat method), (V, 2) mesh units.

        Each vertex as a tangent vector at ``source``: its direction is the direction of the
        geodesic from ``source`` and its length the geodesic distance, in a tangent basis
        that turns counter-clockwise about the outward normal (faces oriented outward).
        Reliable up to the cut locus of ``source``.

        References
        ----------
        .. [1] Sharp, N., Soliman, Y. & Crane, K. "The vector heat method." ACM TOG 38(3),
           2019. doi:10.1145/3243651
        """
        if self._vector_solver is None:
            self._vector_solver = pp3d.MeshVectorHeatSolver(self._vertices, self._faces)
        return np.asarray(self._vector_solver.compute_log_map(int(source)), float)

    def distance(self, source: int) -> np.ndarray:
        """Geodesic distance from vertex ``source`` to every vertex, (V,) mesh units."""
        return np.maximum(self._solver.compute_distance(int(source)), 0.0)

    def distance_multi(self, sources: ArrayLike) -> np.ndarray:
        """Geodesic distance from the nearest of ``sources`` to every vertex, (V,)."""
        return np.maximum(
            self._solver.compute_distance_multisource(np.asarray(sources, np.int64).tolist()), 0.0
        )
