"""Shared geometry on plain arrays: the one place for each piece of mathematics.

* :func:`similarity_fit`, :class:`Similarity`: least-squares similarity of paired points
  (Umeyama), proper rotations unless asked;
* :func:`generalised_procrustes`, :func:`procrustes_mean`, :func:`procrustes_disparity`:
  Procrustes analysis of landmark configurations, never with reflections;
* :func:`face_areas`, :func:`face_normals`, :func:`vertex_areas`, :func:`vertex_normals`,
  :func:`cotangent_laplacian`: triangle meshes;
* :func:`farthest_point_sampling` (Euclidean), :func:`geodesic_farthest_point_sampling`,
  :class:`GeodesicSolver`: sampling and geodesics;
* :func:`principal_frame`, :func:`principal_axes_candidates`, :func:`icp_similarity`,
  :func:`icp_affine`, :func:`cpd_nonrigid`: point-set registration.

Points are ``(N, 3)`` float arrays in one frame and unit (mm for anatomy); nothing here knows
images, files or models.
"""

from medseg.geometry._geodesics import GeodesicSolver
from medseg.geometry._mesh import (
    cotangent_laplacian,
    face_areas,
    face_normals,
    vertex_areas,
    vertex_normals,
)
from medseg.geometry._procrustes import (
    ProcrustesAlignment,
    generalised_procrustes,
    procrustes_disparity,
    procrustes_mean,
)
from medseg.geometry._registration import (
    CPDResult,
    cpd_nonrigid,
    icp_affine,
    icp_similarity,
    principal_axes_candidates,
    principal_frame,
)
from medseg.geometry._sampling import farthest_point_sampling, geodesic_farthest_point_sampling
from medseg.geometry._similarity import Similarity, similarity_fit

__all__ = [
    "Similarity",
    "similarity_fit",
    "ProcrustesAlignment",
    "generalised_procrustes",
    "procrustes_mean",
    "procrustes_disparity",
    "face_areas",
    "face_normals",
    "vertex_areas",
    "vertex_normals",
    "cotangent_laplacian",
    "GeodesicSolver",
    "farthest_point_sampling",
    "geodesic_farthest_point_sampling",
    "principal_frame",
    "principal_axes_candidates",
    "icp_similarity",
    "icp_affine",
    "cpd_nonrigid",
    "CPDResult",
]
