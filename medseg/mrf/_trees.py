"""Cover the factors of a factor graph with few factor trees (no cycle through factors)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["factor_tree_cover", "is_factor_forest"]


def _find(parent: list[int], v: int) -> int:
    root = v
    while parent[root] != root:
        root = parent[root]
    while parent[v] != root:  # path compression
        parent[v], v = root, parent[v]
    return root


def factor_tree_cover(scopes: Sequence[Sequence[int]], n_variables: int) -> np.ndarray:
    """Assign every factor to one factor tree, greedily (first fit), with few trees.

    A set of factors forms a factor tree (or forest) when its bipartite variable-factor
    graph has no cycle: every factor joins variables that lie in pairwise different
    connected components of the factors already in the tree. Factors are taken in the given
    order and put in the first tree where they fit (union-find per tree); a new tree is
    opened when none fits.

    Parameters
    ----------
    scopes : sequence of F sequences of int
        Variables of each factor (order >= 2; orders may be mixed).
    n_variables : int

    Returns
    -------
    (F,) int64 array
        Tree index of each factor, ``0 .. n_trees - 1``.

    Notes
    -----
    A tree over ``N`` variables holds at most ``N - 1`` pairwise or ``(N - 1) // 2``
    triplet factors, so all ``C(N, 3)`` triplets need at least ``(N - 2) N / 6`` trees; the
    greedy cover stays close to that bound in practice.
    """
    trees: list[list[int]] = []  # union-find parent array per tree
    merges: list[int] = []
    tree_of = np.empty(len(scopes), dtype=np.int64)
    first_open = 0
    for f, scope in enumerate(scopes):
        scope = [int(v) for v in scope]
        t = first_open
        while True:
            if t == len(trees):
                trees.append(list(range(n_variables)))
                merges.append(0)
            parent = trees[t]
            roots = [_find(parent, v) for v in scope]
            if len(set(roots)) == len(roots):
                for r in roots[1:]:
                    parent[r] = roots[0]
                merges[t] += len(roots) - 1
                tree_of[f] = t
                break
            t += 1
        while first_open < len(trees) and merges[first_open] >= n_variables - 1:
            first_open += 1  # spanning tree: nothing more fits
    return tree_of


def is_factor_forest(scopes: Sequence[Sequence[int]], n_variables: int) -> bool:
    """Whether the factors' variable-factor graph has no cycle.

    Parameters
    ----------
    scopes : sequence of sequences of int
    n_variables : int

    Returns
    -------
    bool
    """
    parent = list(range(n_variables))
    for scope in scopes:
        roots = [_find(parent, int(v)) for v in scope]
        if len(set(roots)) != len(roots):
            return False
        for r in roots[1:]:
            parent[r] = roots[0]
    return True
