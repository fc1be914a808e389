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
from medseg.matching._mesh import MESH_SUFFIXES, check_mesh, read_mesh, write_mesh

__all__ = [
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
