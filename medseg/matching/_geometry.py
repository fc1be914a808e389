"""Differential geometry of triangle meshes: areas, normals, curvature, Laplacian, HKS,
geodesics and farthest-point sampling.

All functions take ``vertices`` (V, 3) float and ``faces`` (F, 3) int arrays that passed
:func:`medseg.matching.check_mesh`; lengths are in the mesh's units.
"""

from __future__ import annotations

import numpy as np
import potpourri3d as pp3d
import scipy.sparse as sp
from numpy.typing import ArrayLike
from scipy.sparse.linalg import eigsh
from sklearn.utils import check_random_state

__all__ = [
    "face_areas",
    "face_normals",
    "vertex_areas",
    "vertex_normals",
    "gaussian_curvature",
    "cotangent_laplacian",
    "laplacian_eigenpairs",
    "heat_kernel_signature",
    "wave_kernel_signature",
    "GeodesicSolver",
    "farthest_point_sampling",
    "mirrored_fraction",
]


def _corners(vertices: np.ndarray, faces: np.ndarray):
    return vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]


def face_areas(vertices: ArrayLike, faces: ArrayLike) -> np.ndarray:
    """Area of each triangle, (F,) float array in squared mesh units."""
    p0, p1, p2 = _corners(np.asarray(vertices, float), np.asarray(faces))
    return 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1)


def face_normals(vertices: ArrayLike, faces: ArrayLike) -> np.ndarray:
    """Unit normal of each triangle (right-hand rule on the face order), (F, 3) float array."""
    p0, p1, p2 = _corners(np.asarray(vertices, float), np.asarray(faces))
    n = np.cross(p1 - p0, p2 - p0)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def vertex_areas(vertices: ArrayLike, faces: ArrayLike) -> np.ndarray:
    """Barycentric (lumped) vertex area: a third of the adjacent triangles' areas, (V,)."""
    faces = np.asarray(faces)
    a = face_areas(vertices, faces)
    return np.bincount(faces.ravel(), weights=np.repeat(a / 3.0, 3), minlength=len(vertices))


def vertex_normals(vertices: ArrayLike, faces: ArrayLike) -> np.ndarray:
    """Area-weighted unit vertex normals, (V, 3) float array."""
    vertices = np.asarray(vertices, float)
    faces = np.asarray(faces)
    p0, p1, p2 = _corners(vertices, faces)
    n = np.cross(p1 - p0, p2 - p0)  # length = 2 * area
    out = np.zeros_like(vertices)
    for c in range(3):
        np.add.at(out, faces[:, c], n)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)


def _corner_angles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Interior angle at each corner, (F, 3) radians."""
    p = [vertices[faces[:, c]] for c in range(3)]
    out = np.empty(faces.shape, dtype=float)
    for c in range(3):
        u = p[(c + 1) % 3] - p[c]
        w = p[(c + 2) % 3] - p[c]
        cos = np.einsum("ij,ij->i", u, w)
        sin = np.linalg.norm(np.cross(u, w), axis=1)
        out[:, c] = np.arctan2(sin, cos)
    return out


def gaussian_curvature(vertices: ArrayLike, faces: ArrayLike) -> np.ndarray:
    """Discrete Gaussian curvature by angle defect over the barycentric vertex area.

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (F, 3) int array

    Returns
    -------
    k : (V,) float array, 1 / (mesh unit)^2
        ``(2 pi - sum of corner angles) / vertex area`` (``pi`` instead of ``2 pi`` on
        boundary vertices is not applied: boundary values are not meaningful).
    """
    vertices = np.asarray(vertices, float)
    faces = np.asarray(faces)
    ang = _corner_angles(vertices, faces)
    total = np.bincount(faces.ravel(), weights=ang.ravel(), minlength=len(vertices))
    return (2 * np.pi - total) / vertex_areas(vertices, faces)


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
    vertices = np.asarray(vertices, float)
    faces = np.asarray(faces)
    n = len(vertices)
    rows, cols, vals = [], [], []
    for c in range(3):
        i, j, k = faces[:, c], faces[:, (c + 1) % 3], faces[:, (c + 2) % 3]
        u = vertices[i] - vertices[k]
        w = vertices[j] - vertices[k]
        cot = np.einsum("ij,ij->i", u, w) / np.maximum(
            np.linalg.norm(np.cross(u, w), axis=1), 1e-300
        )
        rows += [i, j]
        cols += [j, i]
        vals += [-0.5 * cot, -0.5 * cot]
    off = sp.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    ).tocsr()
    lap = off - sp.diags(np.asarray(off.sum(axis=1)).ravel())
    return lap.tocsr(), sp.diags(vertex_areas(vertices, faces))


def laplacian_eigenpairs(
    vertices: ArrayLike, faces: ArrayLike, *, n_eigen: int = 100
) -> tuple[np.ndarray, np.ndarray]:
    """Lowest eigenpairs of the Laplace-Beltrami operator, ``L phi = lambda M phi``.

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (F, 3) int array
    n_eigen : int
        Number of eigenpairs (including the constant one), at most V - 1.

    Returns
    -------
    evals : (n_eigen,) float array, ascending, 1 / (mesh unit)^2
    evecs : (V, n_eigen) float array, M-orthonormal.
    """
    lap, mass = cotangent_laplacian(vertices, faces)
    k = int(min(n_eigen, lap.shape[0] - 1))
    evals, evecs = eigsh(lap.tocsc(), k=k, M=mass.tocsc(), sigma=-1e-8, which="LM")
    order = np.argsort(evals)
    return np.maximum(evals[order], 0.0), evecs[:, order]


def heat_kernel_signature(
    evals: ArrayLike, evecs: ArrayLike, *, n_scales: int = 16, times: ArrayLike | None = None
) -> np.ndarray:
    """Heat kernel signature, scale-normalised, at log-spaced diffusion times.

    Parameters
    ----------
    evals : (K,) float array
        Laplace-Beltrami eigenvalues (ascending, the first is 0).
    evecs : (V, K) float array
        Mass-orthonormal eigenvectors.
    n_scales : int
        Number of diffusion times when ``times`` is not given: log-spaced between
        ``4 ln 10 / lambda_max`` and ``4 ln 10 / lambda_1`` (Sun, Ovsjanikov & Guibas 2009).
    times : (T,) float array, optional
        Diffusion times in (mesh unit)^2.

    Returns
    -------
    hks : (V, T) float array
        ``sum_k exp(-lambda_k t) phi_k(x)^2``, each column divided by its area-free
        normaliser ``sum_k exp(-lambda_k t)``, so the signature does not depend on the
        mesh's scale or sampling density once the times are scaled with the area.

    References
    ----------
    .. [1] Sun, J., Ovsjanikov, M. & Guibas, L. "A concise and provably informative
       multi-scale signature based on heat diffusion." SGP 2009.
       doi:10.1111/j.1467-8659.2009.01515.x
    """
    evals = np.asarray(evals, float)
    evecs = np.asarray(evecs, float)
    if times is None:
        lo, hi = evals[1] if len(evals) > 1 else 1.0, evals[-1]
        times = np.geomspace(4 * np.log(10) / hi, 4 * np.log(10) / lo, n_scales)
    times = np.asarray(times, float)
    weights = np.exp(-np.outer(evals, times))  # (K, T)
    hks = (evecs**2) @ weights
    return hks / weights.sum(axis=0, keepdims=True)


def wave_kernel_signature(
    evals: ArrayLike,
    evecs: ArrayLike,
    *,
    n_energies: int = 100,
    energy_range: tuple[float, float] | None = None,
    sigma: float = 7.0,
) -> np.ndarray:
    """Wave kernel signature at log-spaced energies.

    Parameters
    ----------
    evals : (K,) float array
        Laplace-Beltrami eigenvalues (ascending, the first is 0 and is skipped).
    evecs : (V, K) float array
        Mass-orthonormal eigenvectors.
    n_energies : int
        Number of energies ``e`` (log-eigenvalues), evenly spaced over ``energy_range``.
    energy_range : (float, float), optional
        Smallest and largest eigenvalue of the band, in 1 / (mesh unit)^2. Default: the
        first non-zero and the last eigenvalue. Pass the same range for two surfaces that
        are compared (e.g. fixed values for unit-area surfaces).
    sigma : float
        Width of the log-normal band filters, in energy steps (Aubry et al. use 7).

    Returns
    -------
    wks : (V, n_energies) float array
        ``sum_k phi_k(x)^2 exp(-(e - log lambda_k)^2 / (2 s^2))``, each column divided by its
        normaliser ``sum_k exp(-(e - log lambda_k)^2 / (2 s^2))``, dimensionless up to the
        vertex density of the eigenvectors (``1 / area`` units; unit-area surfaces compare).

    References
    ----------
    .. [1] Aubry, M., Schlickewei, U. & Cremers, D. "The wave kernel signature: a quantum
       mechanical approach to shape analysis." ICCV Workshops 2011.
       doi:10.1109/ICCVW.2011.6130444
    """
    evals = np.asarray(evals, float)[1:]
    evecs = np.asarray(evecs, float)[:, 1:]
    log_l = np.log(np.maximum(evals, 1e-12))
    lo, hi = (log_l[0], log_l[-1]) if energy_range is None else np.log(energy_range)
    energies = np.linspace(lo, hi, int(n_energies))
    s = sigma * (energies[1] - energies[0]) if len(energies) > 1 else 1.0
    weights = np.exp(-((energies[None, :] - log_l[:, None]) ** 2) / (2 * s**2))  # (K, E)
    return (evecs**2) @ weights / np.maximum(weights.sum(axis=0, keepdims=True), 1e-300)


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


def farthest_point_sampling(
    vertices: ArrayLike,
    faces: ArrayLike,
    n_samples: int,
    *,
    geodesic: GeodesicSolver | None = None,
    random_state=None,
) -> np.ndarray:
    """Farthest-point sampling in geodesic distance.

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (F, 3) int array
    n_samples : int
        Number of vertices to pick (at most V).
    geodesic : GeodesicSolver, optional
        Reuse a factorised solver.
    random_state : int, RandomState or None
        Picks the first sample.

    Returns
    -------
    idx : (n_samples,) int array
        Vertex indices, in the order they were picked.
    """
    rng = check_random_state(random_state)
    n = len(vertices)
    n_samples = int(min(n_samples, n))
    solver = geodesic if geodesic is not None else GeodesicSolver(vertices, faces)
    idx = [int(rng.randint(n))]
    dist = solver.distance(idx[0])
    # restart from the farthest point of a random seed, so the set does not hinge on it
    idx = [int(np.argmax(dist))]
    dist = solver.distance(idx[0])
    for _ in range(1, n_samples):
        nxt = int(np.argmax(dist))
        idx.append(nxt)
        dist = np.minimum(dist, solver.distance(nxt))
    return np.asarray(idx, dtype=np.int64)


def mirrored_fraction(
    vertices_a: ArrayLike,
    faces_a: ArrayLike,
    vertices_b: ArrayLike,
    normals_b: ArrayLike,
    forward: ArrayLike,
) -> float:
    """Share of surface A whose image under a vertex map is mirrored on surface B.

    A face ``(i, j, k)`` of A is sent to the triangle ``(T(i), T(j), T(k))`` of B's
    vertices; the image is mirrored when its right-hand normal points against B's outward
    normals there. An orientation-preserving map (every isometry between two outward
    oriented surfaces that is not a reflection) mirrors few faces, its reflection almost
    all of them.

    Parameters
    ----------
    vertices_a : (V_A, 3) float array
    faces_a : (F_A, 3) int array
        Outward oriented (:func:`medseg.matching.check_mesh`).
    vertices_b : (V_B, 3) float array
    normals_b : (V_B, 3) float array
        Outward unit normals of B (smoothed normals are more robust to noise).
    forward : (V_A,) int array
        Vertex of B matched to each vertex of A.

    Returns
    -------
    fraction : float
        Area of the faces of A with a mirrored image over the area of the faces whose
        image is a triangle (three distinct vertices of B), in [0, 1]; NaN when no image
        is.
    """
    va = np.asarray(vertices_a, float)
    fa = np.asarray(faces_a)
    vb = np.asarray(vertices_b, float)
    nb = np.asarray(normals_b, float)
    tri = np.asarray(forward)[fa]  # (F_A, 3) vertices of B
    q0, q1, q2 = vb[tri[:, 0]], vb[tri[:, 1]], vb[tri[:, 2]]
    image = np.cross(q1 - q0, q2 - q0)
    side = np.einsum("ij,ij->i", image, nb[tri].sum(axis=1))
    distinct = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 2] != tri[:, 0])
    weight = face_areas(va, fa) * distinct
    if weight.sum() == 0:
        return float("nan")
    return float(weight[side < 0].sum() / weight.sum())
