"""Exact min-sum belief propagation on many factor trees at once, batched by depth."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from medseg.mrf._kernels import chunks, min_to_axis

__all__ = ["Forest", "build_forest", "upward", "decode", "copy_min_marginals"]


@dataclass
class Forest:
    """Factor trees laid out for batched message passing.

    Every tree holds its own *copy* of each variable it touches. Factors are reordered (per
    order ``k``) so that the factors at the same depth whose parent copy sits at the same
    table position form one contiguous block.

    Attributes
    ----------
    n_copies : int
    copy_var : (M,) int64 array
        Variable of each copy.
    copy_count : (N,) int64 array
        Number of copies (trees) of each variable; 0 for a variable without factors.
    perm : dict of int -> (C_k,) int64 array
        Working order of the factors of order ``k`` (indices into the MRF's group).
    fcopies : dict of int -> (C_k, k) int64 array
        Copies joined by each factor, in working order.
    levels : list of list of (k, p, slice)
        Blocks by depth (root level first): factors of order ``k`` at that depth whose
        parent copy is at table position ``p``.
    roots : (R,) int64 array
        One root copy per connected component of each tree.
    n_trees : int
    """

    n_copies: int
    copy_var: np.ndarray
    copy_count: np.ndarray
    perm: dict[int, np.ndarray]
    fcopies: dict[int, np.ndarray]
    levels: list[list[tuple[int, int, slice]]]
    roots: np.ndarray
    n_trees: int
    n_factors: dict[int, int] = field(default_factory=dict)


def build_forest(
    scopes: dict[int, np.ndarray], tree_of: dict[int, np.ndarray], n_variables: int
) -> Forest:
    """Lay out factor trees for :func:`upward` and :func:`decode`.

    Parameters
    ----------
    scopes : dict of int -> (C_k, k) int array
        Factor scopes by order.
    tree_of : dict of int -> (C_k,) int array
        Tree index of each factor; the factors of one tree must form a factor forest.
    n_variables : int

    Returns
    -------
    Forest
    """
    orders = sorted(scopes)
    n_trees = int(max((t.max() + 1 for t in tree_of.values() if t.size), default=0))
    keys = np.concatenate(
        [(tree_of[k][:, None] * n_variables + scopes[k]).ravel() for k in orders]
        + [np.empty(0, dtype=np.int64)]
    )
    uniq, inv = np.unique(keys, return_inverse=True)
    n_copies = len(uniq)
    copy_var = (uniq % n_variables).astype(np.int64)
    copy_count = np.bincount(copy_var, minlength=n_variables).astype(np.int64)
    fc_orig, offset = {}, 0
    for k in orders:
        c = len(scopes[k])
        fc_orig[k] = inv[offset : offset + c * k].reshape(c, k)
        offset += c * k
    # global factor list for the traversal
    gl_copies = [fc_orig[k][i].tolist() for k in orders for i in range(len(scopes[k]))]
    n_f = len(gl_copies)
    inc_copy = np.concatenate([fc_orig[k].ravel() for k in orders] + [np.empty(0, np.int64)])
    inc_fac = np.concatenate(
        [np.repeat(np.arange(len(gl_copies)), [len(c) for c in gl_copies])]
        if n_f
        else [np.empty(0, np.int64)]
    )
    srt = np.argsort(inc_copy, kind="stable")
    adj_fac = inc_fac[srt].tolist()
    indptr = np.concatenate([[0], np.cumsum(np.bincount(inc_copy, minlength=n_copies))]).tolist()

    depth = [-1] * n_copies
    f_level = [-1] * n_f
    f_ppos = [0] * n_f
    roots = []
    for c0 in range(n_copies):
        if depth[c0] >= 0:
            continue
        roots.append(c0)
        depth[c0] = 0
        stack = [c0]
        while stack:
            c = stack.pop()
            for f in adj_fac[indptr[c] : indptr[c + 1]]:
                if f_level[f] >= 0:
                    continue
                f_level[f] = depth[c]
                members = gl_copies[f]
                f_ppos[f] = members.index(c)
                for d in members:
                    if d != c:
                        if depth[d] >= 0:
                            raise ValueError("the factors of a tree contain a cycle")
                        depth[d] = depth[c] + 1
                        stack.append(d)

    f_level_arr = np.asarray(f_level, dtype=np.int64)
    f_ppos_arr = np.asarray(f_ppos, dtype=np.int64)
    n_levels = int(f_level_arr.max()) + 1 if n_f else 0
    levels: list[list[tuple[int, int, slice]]] = [[] for _ in range(n_levels)]
    perm, fcopies, offset = {}, {}, 0
    for k in orders:
        c = len(scopes[k])
        lev = f_level_arr[offset : offset + c]
        ppos = f_ppos_arr[offset : offset + c]
        offset += c
        key = lev * k + ppos
        p = np.argsort(key, kind="stable")
        perm[k] = p
        fcopies[k] = fc_orig[k][p]
        sk = key[p]
        starts = np.flatnonzero(np.r_[True, sk[1:] != sk[:-1]])
        ends = np.r_[starts[1:], c]
        for s, e in zip(starts.tolist(), ends.tolist(), strict=True):
            levels[int(sk[s]) // k].append((k, int(sk[s]) % k, slice(s, e)))
    return Forest(
        n_copies=n_copies,
        copy_var=copy_var,
        copy_count=copy_count,
        perm=perm,
        fcopies=fcopies,
        levels=levels,
        roots=np.asarray(roots, dtype=np.int64),
        n_trees=n_trees,
        n_factors={k: len(scopes[k]) for k in orders},
    )


def upward(
    forest: Forest, tables: dict[int, np.ndarray], theta: np.ndarray, dtype=np.float32
) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Leaves-to-root min-sum pass over every tree at once.

    Parameters
    ----------
    forest : Forest
    tables : dict of int -> (C_k, L, ..., L) float32 array
        Working tables (in ``forest.perm`` order, forbidden entries finite).
    theta : (M, L) array
        Unary cost of each copy.
    dtype : numpy dtype
        Arithmetic precision (float32 for speed; float64 for the final certificate).

    Returns
    -------
    bel : (M, L) array
        Cost of each copy's subtree as a function of its label; ``bel[roots].min(1)`` are
        the trees' minima.
    msgs : dict of int -> (C_k, L) array
        Message of each factor to its parent copy.
    """
    bel = np.array(theta, dtype=dtype)
    lab = bel.shape[1]
    msgs = {k: np.empty((n, lab), dtype=dtype) for k, n in forest.n_factors.items()}
    for level in reversed(forest.levels):
        for k, p, sl in level:
            fc = forest.fcopies[k][sl]
            tab = tables[k][sl]
            out = msgs[k][sl]
            for ch in chunks(len(fc), lab**k * np.dtype(dtype).itemsize):
                t = tab[ch] if dtype == tab.dtype else tab[ch].astype(dtype)
                out[ch] = min_to_axis(t, {q: bel[fc[ch, q]] for q in range(k) if q != p}, p)
            np.add.at(bel, fc[:, p], out)
    return bel, msgs


def decode(forest: Forest, tables: dict[int, np.ndarray], bel: np.ndarray) -> np.ndarray:
    """Root-to-leaves argmin: an optimal labelling of every copy in its own tree.

    Returns
    -------
    (M,) int64 array
    """
    x = np.zeros(forest.n_copies, dtype=np.int64)
    x[forest.roots] = bel[forest.roots].argmin(axis=1)
    lab = bel.shape[1]
    for level in forest.levels:
        for k, p, sl in level:
            fc = forest.fcopies[k][sl]
            n = len(fc)
            sliced = np.moveaxis(tables[k][sl], p + 1, 1)[np.arange(n), x[fc[:, p]]]
            children = [q for q in range(k) if q != p]
            acc = sliced
            for j, q in enumerate(children):
                shape = [n] + [1] * (k - 1)
                shape[j + 1] = lab
                acc = acc + bel[fc[:, q]].reshape(shape)
            flat = acc.reshape(n, -1).argmin(axis=1)
            labels = np.unravel_index(flat, (lab,) * (k - 1))
            for j, q in enumerate(children):
                x[fc[:, q]] = labels[j]
    return x


def copy_min_marginals(
    forest: Forest,
    tables: dict[int, np.ndarray],
    bel: np.ndarray,
    msgs: dict[int, np.ndarray],
) -> np.ndarray:
    """Min-marginals of every copy in its own tree (root-to-leaves pass after :func:`upward`).

    Returns
    -------
    (M, L) array, in the dtype of ``bel``
        ``mm[c, l]`` = minimum of copy ``c``'s tree energy with ``x_c = l``.
    """
    out = np.zeros_like(bel)
    lab = bel.shape[1]
    dtype = bel.dtype
    for level in forest.levels:
        for k, p, sl in level:
            fc = forest.fcopies[k][sl]
            tab = tables[k][sl]
            ext = bel[fc[:, p]] + out[fc[:, p]] - msgs[k][sl]
            for ch in chunks(len(fc), lab**k * dtype.itemsize):
                t = tab[ch] if dtype == tab.dtype else tab[ch].astype(dtype)
                for q in range(k):
                    if q == p:
                        continue
                    beliefs = {r: bel[fc[ch, r]] for r in range(k) if r not in (p, q)}
                    beliefs[p] = ext[ch]
                    out[fc[ch, q]] = min_to_axis(t, beliefs, q)
    return bel + out
