"""Block-coordinate dual ascent (MPLP factor updates) over colour classes of factors."""

from __future__ import annotations

import numpy as np

from medseg.mrf._decode import sequential_decode
from medseg.mrf._kernels import (
    all_min_marginals,
    beliefs,
    chunks,
    forbidden_cost,
    working_tables,
)
from medseg.mrf._model import MRF
from medseg.mrf._primal import Clock, PrimalTracker, certified_result, gap_closed
from medseg.mrf._result import SolveResult

__all__ = ["solve_mplp", "colour_factors"]


def colour_factors(scopes: list[list[int]]) -> np.ndarray:
    """Greedy colouring: factors of one colour share no variable.

    Parameters
    ----------
    scopes : list of F lists of int

    Returns
    -------
    (F,) int64 array
        Colour of each factor (smallest colour free on all its variables).
    """
    used: dict[int, int] = {}  # variable -> bitmask of colours already used on it
    colour = np.empty(len(scopes), dtype=np.int64)
    for f, scope in enumerate(scopes):
        taken = 0
        for v in scope:
            taken |= used.get(v, 0)
        c = (~taken & (taken + 1)).bit_length() - 1
        colour[f] = c
        for v in scope:
            used[v] = used.get(v, 0) | (1 << c)
    return colour


def _incidence(scopes: dict[int, np.ndarray], n: int) -> list[list[tuple[int, int, np.ndarray]]]:
    """For every variable, the (order, position, factor indices) of its factors."""
    lists: list[list[tuple[int, int, np.ndarray]]] = [[] for _ in range(n)]
    for k, sc in scopes.items():
        for q in range(k):
            order = np.argsort(sc[:, q], kind="stable")
            bounds = np.searchsorted(sc[order, q], np.arange(n + 1))
            for i in np.flatnonzero(np.diff(bounds)):
                lists[i].append((k, q, order[bounds[i] : bounds[i + 1]]))
    return lists


def _dual_certificate(theta, scopes, tables, lam, n, lab):
    """Exact (float64) dual value and min-marginal lower bounds for multipliers ``lam``."""
    belief = beliefs(theta, scopes, lam)
    lower = float(belief.min(axis=1).sum())
    extra = np.zeros((n, lab))
    for k in scopes:
        fmins = np.empty(len(scopes[k]))
        for ch in chunks(len(scopes[k]), 2 * lab**k * 8):
            t = tables[k][ch].astype(np.float64)
            mm, fmin = all_min_marginals(t, [-lam[k][ch, q] for q in range(k)])
            fmins[ch] = fmin
            for q in range(k):
                np.add.at(extra, scopes[k][ch, q], mm[q] - fmin[:, None])
        lower += float(fmins.sum())
    mm = lower + (belief - belief.min(axis=1, keepdims=True)) + extra
    return lower, mm


def solve_mplp(
    mrf: MRF,
    *,
    max_iter: int,
    tol: float,
    atol: float,
    time_limit: float | None,
    patience: int,
    stall_tol: float,
    local_search: bool,
    progress,
    warm_start: dict[int, np.ndarray] | None = None,
    decode_every: int = 5,
) -> SolveResult:
    """MPLP dual coordinate ascent; see :func:`medseg.mrf.solve`.

    One iteration is a sweep over colour classes; within a class the factors share no
    variable, so their MPLP updates are exact block-coordinate steps done as one batch.
    ``warm_start``: multipliers ``{k: (F_k, k, L)}`` in the MRF's factor order to start from
    (zeros by default); the result's ``multipliers`` are the final ones, in the same order.
    """
    clock = Clock(time_limit)
    n, lab = mrf.unaries.shape
    big = forbidden_cost(mrf)
    theta = np.minimum(mrf.unaries, big)
    orders = sorted(mrf.groups)
    flat = [s for k in orders for s in mrf.groups[k].scopes.tolist()]
    colour = colour_factors(flat)
    n_colours = int(colour.max()) + 1 if len(colour) else 0
    perm, scopes, tables, lam = {}, {}, {}, {}
    blocks: list[list[tuple[int, slice]]] = [[] for _ in range(n_colours)]
    offset = 0
    for k in orders:
        g = mrf.groups[k]
        col = colour[offset : offset + len(g)]
        offset += len(g)
        perm[k] = np.argsort(col, kind="stable")
        scopes[k] = g.scopes[perm[k]]
        tables[k] = working_tables(g.tables, perm[k], big)
        if warm_start is None:
            lam[k] = np.zeros((len(g), k, lab))
        else:
            lam[k] = np.array(warm_start[k][perm[k]], dtype=np.float64)
        sc = col[perm[k]]
        starts = np.flatnonzero(np.r_[True, sc[1:] != sc[:-1]])
        for s, e in zip(starts.tolist(), np.r_[starts[1:], len(g)].tolist(), strict=True):
            blocks[int(sc[s])].append((k, slice(s, e)))

    belief = beliefs(theta, scopes, lam)  # kept up to date by every factor update
    primal = PrimalTracker(mrf, local_search=local_search)
    best_lb = -np.inf
    hist_e, hist_lb = [], []
    status, it = 1, 0
    for it in range(1, max_iter + 1):
        for colour_blocks in blocks:
            for k, sl in colour_blocks:
                sc = scopes[k][sl]
                lk = lam[k][sl]
                rest = belief[sc] - lk  # (n, k, L): each variable's belief without this factor
                rest32 = rest.astype(np.float32)
                for ch in chunks(len(sc), lab**k * 4):
                    mm, _ = all_min_marginals(tables[k][sl][ch], [rest32[ch, q] for q in range(k)])
                    for q in range(k):
                        share = mm[q].astype(np.float64) / k
                        lk[ch, q] = share - rest[ch, q]
                        belief[sc[ch, q]] = share
        # after a full sweep every reparametrised factor has minimum 0: the bound is cheap
        lb = float(belief.min(axis=1).sum())
        primal.offer(belief.argmin(axis=1))
        if it % decode_every == 1 or decode_every == 1:
            primal.offer(sequential_decode(belief, scopes, tables, lam))
        best_lb = max(best_lb, lb)
        hist_e.append(primal.energy)
        hist_lb.append(best_lb)
        progress.update(1)
        if gap_closed(primal.energy, best_lb, tol, atol):
            status = 0
            break
        if it > patience and hist_lb[-1] - hist_lb[-1 - patience] <= stall_tol * max(
            abs(primal.energy), atol
        ):
            status = 2
            break
        if clock.out_of_time():
            status = 3
            break

    lower, mm = _dual_certificate(theta, scopes, tables, lam, n, lab)
    multipliers = {}
    for k in orders:
        multipliers[k] = np.empty_like(lam[k])
        multipliers[k][perm[k]] = lam[k]
    return certified_result(
        mrf,
        primal,
        lower,
        mm,
        big=big,
        status=status,
        n_iter=it,
        clock=clock,
        tol=tol,
        atol=atol,
        history=(hist_e, hist_lb),
        method="mplp",
        n_colours=n_colours,
        multipliers=multipliers,
    )
