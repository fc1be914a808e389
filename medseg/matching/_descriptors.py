"""Intrinsic descriptors of triangle meshes for matching: curvature, Laplace-Beltrami
eigenpairs, heat and wave kernel signatures, and the mirror test of a vertex map.

Areas, normals, the Laplacian, geodesics and sampling are :mod:`medseg.geometry`'s.

All functions take ``vertices`` (V, 3) float and ``faces`` (F, 3) int arrays that passed
:func:`medseg.matching.check_mesh`; lengths are in the mesh's units.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse.linalg import eigsh, splu

from medseg.geometry import cotangent_laplacian, face_areas, vertex_areas

__all__ = [
    "gaussian_curvature",
    "mean_curvature",
    "laplacian_eigenpairs",
    "heat_kernel_signature",
    "wave_kernel_signature",
    "mirrored_fraction",
]


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


def mean_curvature(
    vertices: ArrayLike,
    faces: ArrayLike,
    normals: ArrayLike,
    *,
    times: ArrayLike = (),
) -> np.ndarray:
    """Signed mean curvature from the cotangent Laplacian, optionally smoothed by heat flow.

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (F, 3) int array
        Outward oriented.
    normals : (V, 3) float array
        Outward unit normals (e.g. :func:`medseg.geometry.vertex_normals`).
    times : sequence of float, optional
        Diffusion times, in (mesh unit)^2, of one implicit heat step each
        (``(M + t L) h_t = M h``); one column per time. Empty (default): the raw curvature.

    Returns
    -------
    h : (V,) or (V, len(times)) float array, 1 / mesh unit
        ``H = (M^-1 L x) . n / 2``: the mean of the principal curvatures, positive where the
        surface is convex (``1 / r`` on a sphere of radius ``r``).

    Notes
    -----
    Extrinsic: bending changes it (at the joints of an articulated shape), but unlike the
    intrinsic HKS and WKS it tells the convex side of a surface from the concave one
    (the chest from the back, the toes from the heels).
    """
    v = np.asarray(vertices, float)
    lap, mass = cotangent_laplacian(v, np.asarray(faces))
    area = mass.diagonal()
    h = 0.5 * np.einsum("ij,ij->i", (lap @ v) / area[:, None], np.asarray(normals, float))
    times = np.asarray(times, float)
    if times.size == 0:
        return h
    rhs = mass @ h
    return np.column_stack([splu((mass + t * lap).tocsc()).solve(rhs) for t in times])


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
