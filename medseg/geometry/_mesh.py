"""Areas, normals and the cotangent Laplacian of triangle meshes.

``vertices`` are (V, 3) float arrays and ``faces`` (F, 3) int arrays whose order gives the
orientation (right-hand rule); lengths are in the mesh's units (mm for label surfaces). The
Laplacian and the vertex areas come from potpourri3d (geometry-central), the rest are one
line of numpy each.
"""

from __future__ import annotations

import numpy as np
import potpourri3d as pp3d
import scipy.sparse as sp
from numpy.typing import ArrayLike

__all__ = [
    "face_areas",
    "face_normals",
    "vertex_areas",
    "vertex_normals",
    "cotangent_laplacian",
]


def _corners(vertices: np.ndarray, faces: np.ndarray):
    return vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]


def _face_cross(vertices: ArrayLike, faces: ArrayLike) -> np.ndarray:
    """``(p1 - p0) x (p2 - p0)`` per face: the normal scaled by twice the area, (F, 3)."""
    p0, p1, p2 = _corners(np.asarray(vertices, float), np.asarray(faces))
    return np.cross(p1 - p0, p2 - p0)


def face_areas(vertices: ArrayLike, faces: ArrayLike) -> np.ndarray:
    """Area of each triangle, (F,) float array in squared mesh units."""
    return 0.5 * np.linalg.norm(_face_cross(vertices, faces), axis=1)


def face_normals(vertices: ArrayLike, faces: ArrayLike) -> np.ndarray:
    """Unit normal of each triangle (right-hand rule on the face order), (F, 3) float array."""
    n = _face_cross(vertices, faces)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def vertex_areas(vertices: ArrayLike, faces: ArrayLike) -> np.ndarray:
    """Barycentric (lumped) vertex area: a third of the adjacent triangles' areas, (V,)."""
    return pp3d.vertex_areas(*_pp3d_mesh(vertices, faces))


def vertex_normals(vertices: ArrayLike, faces: ArrayLike) -> np.ndarray:
    """Area-weighted unit vertex normals, (V, 3) float array (zero for isolated vertices)."""
    vertices = np.asarray(vertices, float)
    faces = np.asarray(faces)
    n = _face_cross(vertices, faces)  # length = 2 * area: the area weighting
    out = np.zeros_like(vertices)
    for c in range(3):
        np.add.at(out, faces[:, c], n)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)


def cotangent_laplacian(
    vertices: ArrayLike, faces: ArrayLike
) -> tuple[sp.csr_matrix, sp.dia_matrix]:
    """Cotangent Laplacian (stiffness) and lumped mass matrix.

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (F, 3) int array

    Returns
    -------
    L : (V, V) sparse CSR matrix
        Symmetric positive semi-definite: ``L[i, j] = -(cot a + cot b) / 2`` on edges,
        rows sum to zero. ``M^{-1} L`` approximates minus the Laplace-Beltrami operator.
    M : (V, V) sparse diagonal matrix
        Barycentric vertex areas.

    References
    ----------
    .. [1] Pinkall, U. & Polthier, K. "Computing discrete minimal surfaces and their
       conjugates." Experimental Mathematics 2(1), 1993. doi:10.1080/10586458.1993.10504266
    """
    v, f = _pp3d_mesh(vertices, faces)
    return sp.csr_matrix(pp3d.cotan_laplacian(v, f)), sp.diags(pp3d.vertex_areas(v, f))


def _pp3d_mesh(vertices: ArrayLike, faces: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """The contiguous float64 / int64 arrays potpourri3d takes."""
    return (
        np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(faces, dtype=np.int64),
    )
