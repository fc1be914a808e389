"""Batched min-sum kernels on stacks of dense factor tables, and shared solver plumbing."""

from __future__ import annotations

import numpy as np

from medseg.mrf._model import MRF

__all__ = [
    "forbidden_cost",
    "working_tables",
    "min_to_axis",
    "all_min_marginals",
    "chunks",
    "beliefs",
]

#: Largest temporary (bytes) a batched kernel allocates at once; blocks are cut to fit.
CHUNK_BYTES = 8 * 2**20


def forbidden_cost(mrf: MRF) -> float:
    """A finite cost larger than the energy of any labelling built from finite entries.

    Forbidden entries (``+inf``) are replaced by this value inside the solvers so that
    messages stay finite; a labelling using one has a higher energy than any feasible one,
    so bounds stay valid.
    """
    total = float(np.abs(np.where(np.isfinite(mrf.unaries), mrf.unaries, 0.0)).max(1).sum())
    for g in mrf.groups.values():
        flat = g.tables.reshape(len(g), -1)
        fin = np.isfinite(flat)
        hi = np.max(flat, axis=1, where=fin, initial=0.0)
        lo = np.min(flat, axis=1, where=fin, initial=0.0)
        total += float(np.maximum(np.abs(hi), np.abs(lo)).astype(np.float64).sum())
    return 10.0 * (total + 1.0)


def working_tables(table: np.ndarray, order: np.ndarray, big: float) -> np.ndarray:
    """Copy of ``table[order]`` (float32) with ``+inf`` replaced by ``big``."""
    out = np.take(table, order, axis=0)
    np.minimum(out, np.float32(big), out=out)
    return out


def beliefs(theta: np.ndarray, scopes: dict, multipliers: dict) -> np.ndarray:
    """``theta`` plus, on every variable, the multipliers of every factor on it (float64).

    ``scopes[k]`` is ``(F_k, k)`` and ``multipliers[k]`` ``(F_k, k, L)``, in the same factor
    order: the reparametrised unaries whose row minima sum to the dual value of a
    reparametrisation whose factors have minimum 0.
    """
    out = np.array(theta, dtype=np.float64)
    for k, sc in scopes.items():
        for q in range(k):
            np.add.at(out, sc[:, q], multipliers[k][:, q])
    return out


def chunks(n: int, per_item_bytes: int):
    """Slices of ``range(n)`` whose temporaries stay under :data:`CHUNK_BYTES`."""
    step = max(1, CHUNK_BYTES // max(per_item_bytes, 1))
    for start in range(0, n, step):
        yield slice(start, min(n, start + step))


def min_to_axis(tables: np.ndarray, beliefs: dict[int, np.ndarray], keep: int) -> np.ndarray:
    """Min-sum message of a batch of factors towards one of their variables.

    Parameters
    ----------
    tables : (n, L, L) or (n, L, L, L) array
        Pairwise or triplet tables after the batch axis.
    beliefs : dict of int -> (n, L) array
        Costs added along every table position except ``keep``.
    keep : int
        Table position (0-based) of the receiving variable.

    Returns
    -------
    (n, L) array
        ``min over x_{-keep} [tables[x] + sum_q beliefs[q][x_q]]``.

    Notes
    -----
    Triplet tables are viewed as ``(n, L, L * L)``: numpy reduces the middle axis as
    element-wise minima of long contiguous rows, and the long last axis with SIMD, several
    times faster than a reduction or a broadcast over a short axis of length ``L``. Only
    the ``L``-times smaller partial results see short axes.
    """
    n, lab = tables.shape[:2]
    if tables.ndim == 3:
        if keep == 0:
            return (tables + beliefs[1][:, None, :]).min(axis=2)
        return (tables + beliefs[0][:, :, None]).min(axis=1)
    flat = tables.reshape(n, lab, lab * lab)
    if keep == 0:
        b12 = (beliefs[1][:, :, None] + beliefs[2][:, None, :]).reshape(n, 1, lab * lab)
        return (flat + b12).min(axis=2)
    over_i = (flat + beliefs[0][:, :, None]).min(axis=1).reshape(n, lab, lab)
    if keep == 1:
        return (over_i + beliefs[2][:, None, :]).min(axis=2)
    return (over_i + beliefs[1][:, :, None]).min(axis=1)


def all_min_marginals(
    tables: np.ndarray, beliefs: list[np.ndarray]
) -> tuple[list[np.ndarray], np.ndarray]:
    """Min-marginals of ``tables + sum_q beliefs[q]`` for every table position at once.

    Parameters
    ----------
    tables : (n, L, L) or (n, L, L, L) array
    beliefs : list of k (n, L) arrays

    Returns
    -------
    mm : list of k (n, L) arrays
        ``mm[q][c, l] = min over x with x_q = l``.
    full_min : (n,) array
        The unconstrained minimum of each factor.
    """
    n, lab = tables.shape[:2]
    if tables.ndim == 3:
        acc = tables + beliefs[1][:, None, :]
        acc += beliefs[0][:, :, None]
        mm = [acc.min(axis=2), acc.min(axis=1)]
    else:
        b12 = (beliefs[1][:, :, None] + beliefs[2][:, None, :]).reshape(n, 1, lab * lab)
        acc = tables.reshape(n, lab, lab * lab) + b12
        acc += beliefs[0][:, :, None]
        over_i = acc.min(axis=1).reshape(n, lab, lab)
        mm = [acc.min(axis=2), over_i.min(axis=2), over_i.min(axis=1)]
    return mm, mm[0].min(axis=1)
