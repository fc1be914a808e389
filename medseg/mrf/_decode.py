"""Sequential decoding of a reparametrised energy: fix the variables one at a time.

The dual solvers (MPLP, SRMP) end every few iterations with multipliers ``lam`` such that
``E(x) = sum_i belief_i(x_i) + sum_f R_f(x_f)`` with ``R_f = T_f - sum_q lam_fq``. Taking
the variables from the most confident to the least, each gets the label minimising its
belief plus, for every factor on it, the smallest ``R_f`` compatible with the labels
already fixed.

The visiting order is known before any label is, so each factor's part in the decision of
the variable it meets first (nothing fixed yet: a plain min-marginal of ``R_f``) is
computed for all factors in one batch; only the later visits, which depend on the labels
fixed before them, run in the loop over variables, each as one gather per order and visit.
"""

from __future__ import annotations

import numpy as np

from medseg.mrf._kernels import all_min_marginals, chunks

__all__ = ["sequential_decode"]


def _visit_plan(sc: np.ndarray, rank: np.ndarray, lab: int):
    """Per factor of one order: its variables' table positions in visiting order."""
    k = sc.shape[1]
    pos = np.argsort(rank[sc], axis=1, kind="stable")  # (F, k): table positions by visit
    stride = lab ** (k - 1 - pos)  # flat-index stride of each of those positions
    return pos, np.take_along_axis(sc, pos, axis=1), stride


def _later_visit(flat, lam, f, earlier, pos, stride, ar):
    """What the loop needs of factors ``f`` at their ``v``-th visit (``v = earlier.shape[1]``).

    Everything but the earlier variables' labels: the flat-index offsets of the receiving
    variable's labels (and of the still free one's), the free variable's multipliers, and the
    sum of the receiver's own multipliers over the factors (the fixed variables' multipliers
    are the same for every label of the receiver and drop out of its choice).
    """
    v = earlier.shape[1]
    offsets = ar[None, :] * stride[:, v, None]
    rows = f[:, None]
    free = None
    if pos.shape[1] > v + 1:
        offsets = offsets[:, :, None] + ar[None, None, :] * stride[:, v + 1, None, None]
        rows = f[:, None, None]
        free = lam[f, pos[:, v + 1]][:, None, :]
    own = lam[f, pos[:, v]].sum(axis=0)
    return flat, rows, earlier, stride[:, :v], offsets, free, own


def sequential_decode(
    belief: np.ndarray,
    scopes: dict[int, np.ndarray],
    tables: dict[int, np.ndarray],
    lam: dict[int, np.ndarray],
) -> np.ndarray:
    """A labelling of ``belief`` plus the reparametrised factors, one variable at a time.

    Parameters
    ----------
    belief : (N, L) float array
        Reparametrised unaries (``theta`` plus every factor's multipliers on the variable).
    scopes : dict of k -> (F_k, k) int array
    tables : dict of k -> (F_k, L, ..., L) float32 array
        Finite working tables (forbidden entries already replaced by a large cost).
    lam : dict of k -> (F_k, k, L) float array
        Multipliers, in the factor order of ``scopes``.

    Returns
    -------
    (N,) int64 array
    """
    n, lab = belief.shape
    srt = np.sort(belief, axis=1)
    margin = srt[:, 1] - srt[:, 0] if lab > 1 else np.zeros(n)
    order = np.argsort(-margin, kind="stable")
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    cost = np.array(belief, dtype=np.float64)
    ar = np.arange(lab)
    # later[i]: for each order and visit, the factors that variable i is visited v-th in
    later: list[list[tuple]] = [[] for _ in range(n)]
    for k, sc in scopes.items():
        if not len(sc):
            continue
        pos, vis, stride = _visit_plan(sc, rank, lab)
        rows = np.arange(len(sc))
        for ch in chunks(len(sc), 2 * lab**k * 4):
            neg = [-lam[k][ch, q].astype(np.float32) for q in range(k)]
            mm, _ = all_min_marginals(tables[k][ch], neg)
            first = np.stack(mm, axis=1)[rows[ch] - ch.start, pos[ch, 0]]
            np.add.at(cost, vis[ch, 0], first)
        flat = tables[k].reshape(len(sc), -1)
        for v in range(1, k):
            by = np.argsort(vis[:, v], kind="stable")
            bounds = np.searchsorted(vis[by, v], np.arange(n + 1))
            for i in np.flatnonzero(np.diff(bounds)):
                f = by[bounds[i] : bounds[i + 1]]
                later[i].append(_later_visit(flat, lam[k], f, vis[f, :v], pos[f], stride[f], ar))
    x = np.full(n, -1, dtype=np.int64)
    for i in order:
        c = cost[i].copy()
        for flat, rows, earlier, strides, offsets, free, own in later[i]:
            # the labels of ``earlier`` were fixed before i: they come earlier in the order
            base = (x[earlier] * strides).sum(axis=1)
            vals = flat[rows, base.reshape((-1,) + (1,) * (offsets.ndim - 1)) + offsets]
            if free is not None:  # one position still free (order 3, second visit)
                vals = (vals - free).min(axis=2)
            c += vals.sum(axis=0) - own
        x[i] = int(np.argmin(c))
    return x
