"""Farthest-point sampling: evenly spread subsets of a point set or of a mesh's vertices.

Two distances, two names: :func:`farthest_point_sampling` is Euclidean (landmarks on a
label surface); :func:`geodesic_farthest_point_sampling` measures along the surface
(the matcher's samples, where a limb close to the torso must not look near).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from sklearn.utils import check_random_state

from medseg.geometry._geodesics import GeodesicSolver

__all__ = ["farthest_point_sampling", "geodesic_farthest_point_sampling"]


def farthest_point_sampling(
    points: np.ndarray, n: int, *, start: int | None = None, random_state=None
) -> np.ndarray:
    """Indices of ``n`` points spread evenly by greedy farthest-point sampling (Euclidean).

    Parameters
    ----------
    points : (M, 3) float array
    n : int, ``n <= M``
    start : int, optional
        First index; default: the point farthest from the centroid (deterministic), or a
        random one if ``random_state`` is given.

    Returns
    -------
    (n,) int array
    """
    points = np.asarray(points, float)
    if start is None:
        if random_state is None:
            start = int(np.argmax(((points - points.mean(0)) ** 2).sum(1)))
        else:
            start = int(check_random_state(random_state).randint(len(points)))
    # Squared distances summed coordinate by coordinate in preallocated buffers: the same
    # sums as ``((points - p) ** 2).sum(1)`` to the bit (so the same samples), about ten
    # times faster than reducing over the short last axis with temporaries.
    columns = [np.ascontiguousarray(points[:, k]) for k in range(3)]
    dist, step, term = (np.empty(len(points)) for _ in range(3))

    def squared_to(i: int, out: np.ndarray) -> None:
        for k, column in enumerate(columns):
            target = out if k == 0 else term
            np.subtract(column, column[i], out=target)
            np.square(target, out=target)
            if k:
                out += term

    idx = np.empty(n, dtype=np.intp)
    idx[0] = start
    squared_to(start, dist)
    for k in range(1, n):
        nxt = int(np.argmax(dist))
        idx[k] = nxt
        squared_to(nxt, step)
        np.minimum(dist, step, out=dist)
    return idx


def geodesic_farthest_point_sampling(
    vertices: ArrayLike,
    faces: ArrayLike,
    n_samples: int,
    *,
    geodesic: GeodesicSolver | None = None,
    sampled: ArrayLike | None = None,
    random_state=None,
) -> np.ndarray:
    """Farthest-point sampling of mesh vertices in geodesic distance (heat method).

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (F, 3) int array
    n_samples : int
        Number of vertices to pick (at most V).
    geodesic : GeodesicSolver, optional
        Reuse a factorised solver.
    sampled : int array, optional
        Vertices counted as sampled already and never picked (a surface's boundary, where
        the descriptors of a part cut away from a whole are unlike the whole's): the first
        sample is then the vertex farthest from them, and ``random_state`` is not used.
    random_state : int, RandomState or None
        Picks the first sample.

    Returns
    -------
    idx : (n_samples,) int array
        Vertex indices, in the order they were picked (fewer if ``sampled`` leaves fewer).
    """
    n = len(vertices)
    solver = geodesic if geodesic is not None else GeodesicSolver(vertices, faces)
    if sampled is not None and len(sampled):
        n_samples = int(min(n_samples, n - len(sampled)))
        dist = solver.distance_multi(np.asarray(sampled))
        idx = []
    else:
        n_samples = int(min(n_samples, n))
        # the farthest point of a random seed, so that the set does not hinge on it
        seed = int(check_random_state(random_state).randint(n))
        idx = [int(np.argmax(solver.distance(seed)))]
        dist = solver.distance(idx[0])
    for _ in range(len(idx), n_samples):
        nxt = int(np.argmax(dist))
        idx.append(nxt)
        dist = np.minimum(dist, solver.distance(nxt))
    return np.asarray(idx, dtype=np.int64)
