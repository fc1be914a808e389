"""Dense non-rigid surface matching with third-order graph matching (Zeng et al., CVPR 2010).

Mesh primitives (areas, normals, the Laplacian, geodesics, sampling) are in
:mod:`medseg.geometry`. The modules, in the order the matcher uses them:

* ``_mesh_io``, ``_mesh_check``: mesh files in and out; the checks a mesh must pass;
* ``_descriptors``, ``_conformal``, ``_surface``: curvature, eigenpairs, HKS / WKS and the
  mirror test; conformal flattening and Möbius transforms; what is computed once per surface;
* ``_potentials``, ``_solver``: the terms of the third-order energy; its minimisation
  (one-to-one by dual decomposition, many-to-one by block-coordinate dual ascent);
* ``_sparse``, ``_voting``, ``_dense``, ``_spectral``: the sparse stage, the dense candidates
  from Möbius votes, the dense stage, the ZoomOut refinement;
* ``_matcher``: :func:`match_surfaces`, the choice among sparse solves;
* ``_scoring``: geodesic error of a map against ground truth (benchmarks, tests).
"""

from medseg.matching._conformal import (
    CANONICAL_TRIPLET,
    apply_mobius,
    close_holes,
    compose_mobius,
    conformal_flatten,
    invert_mobius,
    mobius_from_triplets,
    mobius_to_canonical,
    to_riemann_sphere,
)
from medseg.matching._descriptors import (
    gaussian_curvature,
    heat_kernel_signature,
    laplacian_eigenpairs,
    mean_curvature,
    mirrored_fraction,
    wave_kernel_signature,
)
from medseg.matching._matcher import SurfaceMatch, match_surfaces
from medseg.matching._mesh_check import check_mesh
from medseg.matching._mesh_io import MESH_SUFFIXES, read_mesh, write_mesh
from medseg.matching._potentials import (
    gaussian_map_potentials,
    geodesic_distortion_potentials,
    intrinsic_orientation,
    mobius_potentials,
    orientation_potentials,
    singleton_potentials,
    triplet_potentials,
)
from medseg.matching._solver import (
    MatchingProblem,
    SolveResult,
    matching_energy,
    solve_many_to_one,
    solve_matching,
)
from medseg.matching._spectral import spectral_refine, spectral_residual
from medseg.matching._surface import PreparedSurface, prepare_surface

__all__ = [
    "MatchingProblem",
    "PreparedSurface",
    "SolveResult",
    "SurfaceMatch",
    "gaussian_map_potentials",
    "geodesic_distortion_potentials",
    "intrinsic_orientation",
    "match_surfaces",
    "matching_energy",
    "mobius_potentials",
    "orientation_potentials",
    "prepare_surface",
    "singleton_potentials",
    "solve_matching",
    "solve_many_to_one",
    "spectral_refine",
    "spectral_residual",
    "triplet_potentials",
    "CANONICAL_TRIPLET",
    "MESH_SUFFIXES",
    "apply_mobius",
    "check_mesh",
    "close_holes",
    "compose_mobius",
    "conformal_flatten",
    "gaussian_curvature",
    "heat_kernel_signature",
    "invert_mobius",
    "laplacian_eigenpairs",
    "mean_curvature",
    "mobius_from_triplets",
    "mirrored_fraction",
    "mobius_to_canonical",
    "read_mesh",
    "to_riemann_sphere",
    "wave_kernel_signature",
    "write_mesh",
]
