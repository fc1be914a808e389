"""What the matcher computes once per surface: :class:`PreparedSurface` and
:func:`prepare_surface`.

Each surface is checked, centred and scaled to unit area; then come its Laplace-Beltrami
eigenpairs, its point descriptor (log HKS and log WKS at fixed times and energies of the
unit-area surface, why both: :mod:`medseg.matching._sparse`), smoothed normals, geodesic
farthest-point samples and conformal flattening.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse.linalg import splu

from medseg.geometry import (
    GeodesicSolver,
    cotangent_laplacian,
    face_areas,
    farthest_point_sampling,
    geodesic_farthest_point_sampling,
    vertex_areas,
    vertex_normals,
)
from medseg.matching._conformal import conformal_flatten
from medseg.matching._descriptors import (
    heat_kernel_signature,
    laplacian_eigenpairs,
    wave_kernel_signature,
)
from medseg.matching._mesh_check import check_mesh

__all__ = ["PreparedSurface", "prepare_surface"]


class _CachedGeodesics(GeodesicSolver):
    """A :class:`GeodesicSolver` that keeps every distance field and log map it computed.

    The farthest-point sampling computes the distance field of every sample; the sparse
    stage, the votes and every further sparse solve ask for the same fields (and log maps)
    again. The arrays returned are read-only views of the cache."""

    def __init__(self, vertices: ArrayLike, faces: ArrayLike):
        super().__init__(vertices, faces)
        self._distances: dict[int, np.ndarray] = {}
        self._log_maps: dict[int, np.ndarray] = {}

    def distance(self, source: int) -> np.ndarray:
        key = int(source)
        if key not in self._distances:
            field = super().distance(key)
            field.flags.writeable = False
            self._distances[key] = field
        return self._distances[key]

    def log_map(self, source: int) -> np.ndarray:
        key = int(source)
        if key not in self._log_maps:
            field = super().log_map(key)
            field.flags.writeable = False
            self._log_maps[key] = field
        return self._log_maps[key]


# diffusion times of the HKS on a unit-area surface
_HKS_TIMES = np.geomspace(5e-3, 1.0, 16)
# WKS band on a unit-area surface: from below the first non-zero eigenvalue of elongated
# shapes to Weyl's estimate 4 pi k of the k-th eigenvalue, for k = n_eigen
_WKS_LOWEST = 2.0
_N_WKS = 100


def _standardise(x: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Columns to zero mean and unit variance under the vertex-area weights."""
    w = weights / weights.sum()
    mean = w @ x
    std = np.sqrt(w @ (x - mean) ** 2)
    return (x - mean) / np.maximum(std, 1e-12)


def _descriptor(v, f, evals, evecs, n_eigen):
    """Log HKS (16 times) and log WKS (100 energies), each column standardised, the WKS
    block weighted so that both blocks carry the same total variance."""
    area = vertex_areas(v, f)
    hks = heat_kernel_signature(evals, evecs, times=_HKS_TIMES)
    wks = wave_kernel_signature(
        evals, evecs, n_energies=_N_WKS, energy_range=(_WKS_LOWEST, 4 * np.pi * n_eigen)
    )
    hks = _standardise(np.log(np.maximum(hks, 1e-12)), area)
    wks = _standardise(np.log(np.maximum(wks, 1e-12)), area)
    return np.hstack([hks, wks * np.sqrt(hks.shape[1] / wks.shape[1])])


@dataclass
class PreparedSurface:
    """Everything the matcher computes once per surface (see :func:`prepare_surface`).

    Attributes
    ----------
    vertices : (V, 3) float array
        Centred and scaled to unit total area (so units do not matter).
    faces : (F, 3) int array, outward oriented.
    scale : float
        ``sqrt(area)`` of the input, in its units.
    z : (V,) complex array
        Conformal flattening.
    normals : (V, 3) float array
        Smoothed outward unit normals.
    descriptor : (V, D) float array
        Log heat kernel signature at 16 fixed times and log wave kernel signature at 100
        fixed energies of the unit-area surface, each column standardised over the surface
        (area-weighted), the two blocks with equal weight.
    evals, evecs : (E,), (V, E) float arrays
        Laplace-Beltrami eigenpairs of the unit-area surface.
    samples : (S,) int array
        Geodesic farthest-point samples, in picking order.
    spectral_samples : (S', ) int array
        Euclidean farthest-point samples (``n_spectral_samples``, from the vertex farthest
        from the centroid), on which the spectral refinement iterates.
    geodesic : GeodesicSolver
        Heat-method geodesics on ``vertices``; it keeps the distance fields and log maps it
        computed (those of the samples from the start), so that later stages and solves
        reuse them.
    """

    vertices: np.ndarray
    faces: np.ndarray
    scale: float
    z: np.ndarray
    normals: np.ndarray
    descriptor: np.ndarray
    evals: np.ndarray
    evecs: np.ndarray
    samples: np.ndarray
    spectral_samples: np.ndarray
    geodesic: GeodesicSolver = field(repr=False)


def prepare_surface(
    vertices: ArrayLike,
    faces: ArrayLike,
    *,
    name: str = "mesh",
    n_samples: int = 120,
    n_eigen: int = 80,
    n_spectral_samples: int = 1000,
    random_state=None,
) -> PreparedSurface:
    """Check a mesh and compute its descriptors, flattening, normals and samples.

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (F, 3) int array
    name : str
        Used in error messages.
    n_samples : int
        Farthest-point samples (the sparse points are the first of them).
    n_eigen : int
        Laplace-Beltrami eigenpairs for the HKS.
    n_spectral_samples : int
        Vertices on which the spectral refinement iterates (at most V).
    random_state : int, RandomState or None

    Returns
    -------
    PreparedSurface
    """
    v, f = check_mesh(vertices, faces, name=name)
    scale = float(np.sqrt(face_areas(v, f).sum()))
    v = (v - v.mean(axis=0)) / scale
    evals, evecs = laplacian_eigenpairs(v, f, n_eigen=n_eigen)
    descriptor = _descriptor(v, f, evals, evecs, n_eigen)
    # smoothed normals: normals of the surface after a short implicit heat flow
    lap, mass = cotangent_laplacian(v, f)
    smooth = splu((mass + 1e-3 * lap).tocsc()).solve(mass @ v)
    normals = vertex_normals(smooth, f)
    geo = _CachedGeodesics(v, f)
    samples = geodesic_farthest_point_sampling(
        v, f, n_samples, geodesic=geo, random_state=random_state
    )
    z = conformal_flatten(v, f)
    spectral = farthest_point_sampling(v, min(n_spectral_samples, len(v)))
    return PreparedSurface(
        v, f, scale, z, normals, descriptor, evals, evecs, samples, np.asarray(spectral), geo
    )
