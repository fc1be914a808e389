"""Choice of the triplet cliques of the shape prior, and the memory their tables need."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import Delaunay, QhullError, cKDTree
from sklearn.utils import check_random_state

from medseg.errors import ParameterError

__all__ = ["select_cliques", "clique_table_size", "CliqueTableSize"]

_METHODS = ("delaunay", "knn", "all")


def _as_points(mean_shape: ArrayLike) -> np.ndarray:
    pts = np.asarray(mean_shape, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 3:
        raise ParameterError(
            f"`mean_shape` must be an (N, 3) array of landmark positions with N >= 3; "
            f"got shape {pts.shape}"
        )
    if not np.all(np.isfinite(pts)):
        raise ParameterError("`mean_shape` contains NaN or infinite coordinates")
    return pts


def _unique_sorted(triples: np.ndarray) -> np.ndarray:
    triples = np.sort(np.asarray(triples, dtype=np.int64).reshape(-1, 3), axis=1)
    triples = triples[(triples[:, 0] != triples[:, 1]) & (triples[:, 1] != triples[:, 2])]
    return np.unique(triples, axis=0)


def _delaunay_faces(pts: np.ndarray, random_state) -> np.ndarray:
    try:
        tets = Delaunay(pts).simplices
    except QhullError:
        # flat or degenerate configurations: jiggle by a tiny, reproducible amount
        rng = check_random_state(random_state)
        scale = np.ptp(pts, axis=0).max() or 1.0
        tets = Delaunay(pts + 1e-6 * scale * rng.standard_normal(pts.shape)).simplices
    faces = np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]],
                            tets[:, [1, 2, 3]]])  # fmt: skip
    return _unique_sorted(faces)


def _knn_triples(pts: np.ndarray, k: int) -> np.ndarray:
    n = len(pts)
    k = min(k, n - 1)
    _, nbr = cKDTree(pts).query(pts, k=k + 1)
    nbr = nbr[:, 1:]
    pairs = np.array(list(combinations(range(k), 2)), dtype=np.intp)
    centre = np.repeat(np.arange(n), len(pairs))
    a = nbr[:, pairs[:, 0]].ravel()
    b = nbr[:, pairs[:, 1]].ravel()
    return _unique_sorted(np.stack([centre, a, b], axis=1))


def select_cliques(
    mean_shape: ArrayLike,
    *,
    method: str = "delaunay",
    k: int = 4,
    max_cliques: int | None = None,
    random_state=None,
) -> np.ndarray:
    """Triplet cliques ``(i, j, k)`` of the shape prior.

    Parameters
    ----------
    mean_shape : (N, 3) float array, mm
        A representative landmark configuration (e.g. the mean training shape).
    method : {"delaunay", "knn", "all"}
        ``"delaunay"``: the triangles (faces) of the Delaunay tetrahedralisation of
        ``mean_shape``, about 6-7 N cliques; ``"knn"``: for each landmark, the triangles it
        forms with any two of its ``k`` nearest neighbours, at most N k (k - 1) / 2 cliques;
        ``"all"``: all N (N - 1) (N - 2) / 6 triplets.
    k : int
        Neighbours per landmark for ``method="knn"``.
    max_cliques : int, optional
        Keep a random subset of at most this many cliques (drawn with ``random_state``).
    random_state : int, RandomState instance or None
        Used for ``max_cliques`` and to break a degenerate (flat) Delaunay configuration.

    Returns
    -------
    cliques : (C, 3) int64 array
        Each row sorted ``i < j < k``; rows unique and in lexicographic order.

    See Also
    --------
    clique_table_size : the count and the memory of the potential tables, before use.
    """
    pts = _as_points(mean_shape)
    if method not in _METHODS:
        raise ParameterError(f"`method` must be one of {_METHODS}; got {method!r}")
    if method == "delaunay":
        if len(pts) < 4:
            cliques = np.array([[0, 1, 2]], dtype=np.int64)
        else:
            cliques = _delaunay_faces(pts, random_state)
    elif method == "knn":
        if int(k) < 2:
            raise ParameterError(f"`k` must be >= 2 for method='knn'; got {k}")
        cliques = _knn_triples(pts, int(k))
    else:
        cliques = np.array(list(combinations(range(len(pts)), 3)), dtype=np.int64)
    if max_cliques is not None:
        if int(max_cliques) < 1:
            raise ParameterError(f"`max_cliques` must be a positive integer; got {max_cliques}")
        if len(cliques) > max_cliques:
            rng = check_random_state(random_state)
            keep = np.sort(rng.choice(len(cliques), size=int(max_cliques), replace=False))
            cliques = cliques[keep]
    return cliques


@dataclass(frozen=True)
class CliqueTableSize:
    """Size of the potential tables of a clique set for ``n_candidates`` per landmark."""

    n_cliques: int
    n_candidates: int
    nbytes: int  # of the (C, L, L, L) float32 table

    def __str__(self) -> str:
        return (
            f"{self.n_cliques} cliques x {self.n_candidates}^3 candidate triples: "
            f"{self.nbytes / 2**20:.1f} MiB of float32 potential tables"
        )


def clique_table_size(cliques: ArrayLike | int, n_candidates: int) -> CliqueTableSize:
    """Count of cliques and memory of their ``(C, L, L, L)`` float32 potential tables.

    Parameters
    ----------
    cliques : (C, 3) int array, or the count C
    n_candidates : int
        Candidates per landmark, L.

    Returns
    -------
    CliqueTableSize
        ``n_cliques``, ``n_candidates`` and ``nbytes``; ``str()`` gives a readable summary.
    """
    c = int(cliques) if np.ndim(cliques) == 0 else int(np.shape(cliques)[0])
    lab = int(n_candidates)
    return CliqueTableSize(n_cliques=c, n_candidates=lab, nbytes=4 * c * lab**3)
