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

from medseg.errors import ProblemDefinitionError
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
from medseg.matching._mesh_check import _boundary_half_edges, check_mesh

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

    @staticmethod
    def _kept(cache: dict, source: int, compute) -> np.ndarray:
        key = int(source)
        if key not in cache:
            cache[key] = compute(key)
            cache[key].flags.writeable = False
        return cache[key]

    def distance(self, source: int) -> np.ndarray:
        return self._kept(self._distances, source, super().distance)

    def log_map(self, source: int) -> np.ndarray:
        return self._kept(self._log_maps, source, super().log_map)


# diffusion times of the HKS on a unit-area surface
_HKS_TIMES = np.geomspace(5e-3, 1.0, 16)
# WKS band on a unit-area surface: from below the first non-zero eigenvalue of elongated
# shapes to Weyl's estimate 4 pi k of the k-th eigenvalue, for k = n_eigen
_WKS_LOWEST = 2.0
_N_WKS = 100


def _signature(v, f, evals, evecs, n_eigen):
    """Log HKS (16 times) and log WKS (100 energies), (V, 116), not standardised."""
    hks = heat_kernel_signature(evals, evecs, times=_HKS_TIMES)
    wks = wave_kernel_signature(
        evals, evecs, n_energies=_N_WKS, energy_range=(_WKS_LOWEST, 4 * np.pi * n_eigen)
    )
    return np.log(np.maximum(np.hstack([hks, wks]), 1e-12))


def _descriptor(signature, weights):
    """Each column of ``signature`` standardised to zero mean and unit variance under
    ``weights`` (the vertex areas), the WKS block weighted so that both blocks carry the
    same total variance."""
    w = weights / weights.sum()
    mean = w @ signature
    std = np.maximum(np.sqrt(w @ (signature - mean) ** 2), 1e-12)
    out = (signature - mean) / std
    out[:, len(_HKS_TIMES) :] *= np.sqrt(len(_HKS_TIMES) / _N_WKS)
    return out


@dataclass
class PreparedSurface:
    """Everything the matcher computes once per surface (see :func:`prepare_surface`).

    Attributes
    ----------
    vertices : (V, 3) float array
        Centred and scaled to unit total area (so units do not matter), or by the given
        ``scale``.
    faces : (F, 3) int array, outward oriented.
    scale : float
        The unit, in the input's units: ``sqrt(area)`` of the input unless given.
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
        Geodesic farthest-point samples, in picking order (on a surface with holes, away
        from their boundary: the boundary counts as sampled).
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
    scale: float | None = None,
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
    scale : float, optional
        Length, in the mesh's units, taken as the unit. Default: ``sqrt(area)``, so that
        the surface has unit area. Two surfaces of which one is part of the other are
        given the same (the larger one's), so that the part keeps its relative size.
    random_state : int, RandomState or None

    Returns
    -------
    PreparedSurface
    """
    v, f = check_mesh(vertices, faces, name=name)
    if scale is None:
        scale = float(np.sqrt(face_areas(v, f).sum()))
    elif not (np.isfinite(scale) and scale > 0):
        raise ProblemDefinitionError(f"scale must be a positive length, got {scale}.")
    scale = float(scale)
    v = (v - v.mean(axis=0)) / scale
    evals, evecs = laplacian_eigenpairs(v, f, n_eigen=n_eigen)
    signature = _signature(v, f, evals, evecs, n_eigen)
    descriptor = _descriptor(signature, vertex_areas(v, f))
    # smoothed normals: normals of the surface after a short implicit heat flow
    lap, mass = cotangent_laplacian(v, f)
    smooth = splu((mass + 1e-3 * lap).tocsc()).solve(mass @ v)
    normals = vertex_normals(smooth, f)
    geo = _CachedGeodesics(v, f)
    # on a surface with holes the samples keep away from their boundary, counted as sampled
    samples = geodesic_farthest_point_sampling(
        v,
        f,
        n_samples,
        geodesic=geo,
        sampled=np.unique(_boundary_half_edges(f)),
        random_state=random_state,
    )
    z = conformal_flatten(v, f)
    spectral = farthest_point_sampling(v, min(n_spectral_samples, len(v)))
    return PreparedSurface(
        v,
        f,
        scale,
        z,
        normals,
        descriptor,
        evals,
        evecs,
        samples,
        np.asarray(spectral),
        geo,
    )
