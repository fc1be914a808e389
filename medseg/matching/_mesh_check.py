"""The checks a triangle mesh must pass before it is matched (:func:`check_mesh`).

A mesh is a pair of plain arrays: ``vertices`` (V, 3) float (x, y, z) and ``faces`` (F, 3)
int, 0-based. The matcher needs a connected, edge-manifold, consistently oriented genus-0
surface; :func:`check_mesh` says what is wrong with any other and orients faces outwards.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from medseg.errors import MeshError

__all__ = ["check_mesh"]


def _check_finite_and_indexed(
    vertices: np.ndarray, faces: np.ndarray, label: str, *, fix_vertices: str, fix_faces: str
) -> None:
    """MeshError if a vertex has a non-finite coordinate or a face index is outside
    ``[0, V)``; ``label`` opens the message, ``fix_vertices`` and ``fix_faces`` end it."""
    bad = ~np.all(np.isfinite(vertices), axis=1)
    if bad.any():
        raise MeshError(
            f"{label}: {int(bad.sum())} vertices have NaN or infinite coordinates (first: vertex "
            f"{int(np.flatnonzero(bad)[0])}); {fix_vertices}."
        )
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(
            f"{label}: face indices must lie in [0, {len(vertices) - 1}] (0-based, "
            f"{len(vertices)} vertices), got range [{faces.min()}, {faces.max()}]{fix_faces}."
        )


def _edges(faces: np.ndarray) -> np.ndarray:
    """Directed half-edges (3F, 2) in face order: (0,1), (1,2), (2,0) of each face."""
    return faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)


def _boundary_half_edges(faces: np.ndarray) -> np.ndarray:
    """The half-edges (B, 2) whose reverse no face has: the boundary, each with its face on
    the left."""
    half = _edges(faces)
    n = int(faces.max()) + 1 if len(faces) else 0
    key = half[:, 0] * n + half[:, 1]
    return half[~np.isin(key, half[:, 1] * n + half[:, 0])]


def check_mesh(
    vertices: ArrayLike,
    faces: ArrayLike,
    *,
    name: str = "mesh",
    allow_boundary: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Check that a mesh can be matched; return it with outward-oriented faces.

    The matcher needs a connected, edge-manifold, consistently oriented triangle mesh of genus
    0: a closed sphere-like surface, or one with holes (boundary loops), which the conformal
    flattening closes with a fan per loop.

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (F, 3) int array, 0-based
    name : str
        How the mesh is named in error messages (e.g. its file name).
    allow_boundary : bool
        Accept meshes with boundary loops (genus 0 with holes). Default True.

    Returns
    -------
    vertices : (V, 3) float array
        Unchanged (a float copy).
    faces : (F, 3) int64 array
        The same triangles; on a closed mesh whose normals point inwards (negative enclosed
        volume) every face is reversed so normals point outwards. This is the only repair:
        vertex indices, hence the output map, never change.

    Raises
    ------
    MeshError
        Non-finite vertices, face indices out of range, degenerate faces (repeated vertex or
        zero area), unreferenced vertices, non-manifold edges, inconsistent orientation, more
        than one connected component, or a genus other than 0; the message says which, how
        many, and what to do.
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4:
        raise MeshError(f"{name}: vertices must be a (V, 3) array with V >= 4, got {v.shape}.")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) < 4:
        raise MeshError(f"{name}: faces must be an (F, 3) array with F >= 4, got {f.shape}.")
    if not np.issubdtype(f.dtype, np.integer):
        if not np.all(np.isfinite(f)) or np.any(f != np.round(f)):
            raise MeshError(f"{name}: face indices must be integers.")
    f = f.astype(np.int64)
    _check_finite_and_indexed(v, f, name, fix_vertices="fix or remove them", fix_faces="")
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    scale = np.ptp(v, axis=0).max() or 1.0
    degenerate = repeated | (area <= 1e-12 * scale**2)
    if degenerate.any():
        raise MeshError(
            f"{name}: {degenerate.sum()} degenerate faces (repeated vertex or zero area; first: "
            f"face {np.flatnonzero(degenerate)[0]}); remove them, e.g. with "
            "pyvista's clean() or a remeshing tool."
        )
    used = np.zeros(len(v), dtype=bool)
    used[f.ravel()] = True
    if not used.all():
        raise MeshError(
            f"{name}: {(~used).sum()} vertices belong to no face (first: "
            f"{np.flatnonzero(~used)[0]}); remove unreferenced vertices."
        )
    half = _edges(f)
    und = np.sort(half, axis=1)
    key = und[:, 0] * len(v) + und[:, 1]
    uniq, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    if (counts > 2).any():
        raise MeshError(
            f"{name}: {(counts > 2).sum()} non-manifold edges (shared by more than two faces); "
            "the matcher needs a manifold surface."
        )
    dkey = half[:, 0] * len(v) + half[:, 1]
    if len(np.unique(dkey)) != len(dkey):
        raise MeshError(
            f"{name}: faces are not consistently oriented (an edge is traversed twice in the "
            "same direction); reorient the faces (e.g. pyvista's compute_normals("
            "consistent_normals=True))."
        )
    n_comp, _ = connected_components(
        coo_matrix((np.ones(len(half)), (half[:, 0], half[:, 1])), shape=(len(v), len(v))),
        directed=False,
    )
    if n_comp != 1:
        raise MeshError(
            f"{name}: mesh has {n_comp} connected components; match one surface at a time "
            "(keep the largest component, e.g. pyvista's connectivity('largest'))."
        )
    n_edges = len(uniq)
    n_boundary_edges = int((counts == 1).sum())
    n_loops = _count_boundary_loops(half, counts[inverse] == 1, len(v))
    euler = len(v) - n_edges + len(f)
    genus2 = 2 - euler - n_loops
    if genus2 != 0:
        raise MeshError(
            f"{name}: surface has genus {genus2 / 2:g} (Euler characteristic {euler}, "
            f"{n_loops} boundary loops); the matcher needs a genus-0 surface (sphere-like, "
            "possibly with holes): close handles or tunnels first."
        )
    if n_boundary_edges and not allow_boundary:
        raise MeshError(f"{name}: surface has {n_loops} holes; a closed surface is required.")
    if n_boundary_edges == 0:
        p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        volume = np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum() / 6.0
        if volume < 0:
            f = f[:, ::-1].copy()
    return v.copy(), f


def _count_boundary_loops(half: np.ndarray, is_boundary: np.ndarray, n_vertices: int) -> int:
    """Number of boundary loops, from the boundary half-edges' connectivity."""
    b = half[is_boundary]
    if len(b) == 0:
        return 0
    graph = coo_matrix((np.ones(len(b)), (b[:, 0], b[:, 1])), shape=(n_vertices, n_vertices))
    _, labels = connected_components(graph, directed=False)
    return len(np.unique(labels[np.unique(b.ravel())]))
