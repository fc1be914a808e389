"""Dense non-rigid surface matching with third-order graph matching (Zeng et al., CVPR 2010)."""

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
from medseg.matching._geometry import (
    GeodesicSolver,
    cotangent_laplacian,
    face_areas,
    face_normals,
    farthest_point_sampling,
    gaussian_curvature,
    heat_kernel_signature,
    laplacian_eigenpairs,
    vertex_areas,
    vertex_normals,
)
from medseg.matching._matcher import (
    PreparedSurface,
    SurfaceMatch,
    match_surfaces,
    prepare_surface,
    spectral_refine,
)
from medseg.matching._mesh import MESH_SUFFIXES, check_mesh, read_mesh, write_mesh
from medseg.matching._potentials import (
    gaussian_map_potentials,
    mobius_potentials,
    singleton_potentials,
    triplet_potentials,
)
from medseg.matching._solver import MatchingProblem, SolveResult, matching_energy, solve_matching

__all__ = [
    "MatchingProblem",
    "PreparedSurface",
    "SolveResult",
    "SurfaceMatch",
    "gaussian_map_potentials",
    "match_surfaces",
    "matching_energy",
    "mobius_potentials",
    "prepare_surface",
    "singleton_potentials",
    "solve_matching",
    "spectral_refine",
    "triplet_potentials",
    "CANONICAL_TRIPLET",
    "MESH_SUFFIXES",
    "GeodesicSolver",
    "apply_mobius",
    "check_mesh",
    "close_holes",
    "compose_mobius",
    "conformal_flatten",
    "cotangent_laplacian",
    "face_areas",
    "face_normals",
    "farthest_point_sampling",
    "gaussian_curvature",
    "heat_kernel_signature",
    "invert_mobius",
    "laplacian_eigenpairs",
    "mobius_from_triplets",
    "mobius_to_canonical",
    "read_mesh",
    "to_riemann_sphere",
    "vertex_areas",
    "vertex_normals",
    "write_mesh",
]
