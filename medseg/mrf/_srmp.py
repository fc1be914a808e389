"""Sequential reweighted message passing (SRMP, Kolmogorov 2015) for factors of order 2-3."""

from __future__ import annotations

import numpy as np

from medseg.mrf._kernels import forbidden_cost, min_to_axis
from medseg.mrf._model import MRF
from medseg.mrf._mplp import _dual_certificate, _incidence, _sequential_decode
from medseg.mrf._primal import (
    Clock,
    PrimalTracker,
    finish_min_marginals,
    gap_closed,
    rounding_slack,
)
from medseg.mrf._result import SolveResult, make_result

__all__ = ["solve_srmp"]


#: The in-factor tables of every variable are stored transposed and contiguous (about
#: ``2 (k - 1)`` copies of the tables) when that fits in this many bytes; otherwise they are
#: gathered on the fly at every visit.
PREGATHER_BYTES = 512 * 2**20


def _transposed(table: np.ndarray, q: int) -> np.ndarray:
    """``table`` (n, L, ..., L) with table position ``q`` moved first (others in order)."""
    k = table.ndim - 1
    return np.transpose(table, (0, 1 + q) + tuple(1 + r for r in range(k) if r != q))


def _stack(table: np.ndarray, parts) -> np.ndarray:
    """C-contiguous stack of ``table[fin]`` with position ``q`` first, for (q, fin) parts."""
    return np.ascontiguousarray(np.concatenate([_transposed(table[fin], q) for q, fin in parts]))


def _pass_plan(scopes, incidence, order, tables, pregather):
    """For each variable (in ``order``): its factors split into incoming / outgoing sets.

    A factor is *incoming* at ``i`` when it has a variable earlier than ``i`` in the order,
    *outgoing* when it has one later; the weight of an outgoing factor is
    ``1 / max(#incoming, #outgoing)`` (Kolmogorov 2015, SRMP). The incoming factors of one
    order are updated as one batch with ``i`` moved to the first table axis.
    """
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    plan = []
    for i in order:
        groups, incoming, n_in, n_out = [], {}, 0, 0
        for k, q, f in incidence[i]:
            others = np.delete(rank[scopes[k][f]], q, axis=1)
            fin = f[(others < rank[i]).any(axis=1)]
            fout = f[(others > rank[i]).any(axis=1)]
            n_in += len(fin)
            n_out += len(fout)
            groups.append((k, q, f, fout))
            if len(fin):
                incoming.setdefault(k, []).append((q, fin))
        batches = []
        for k, parts in incoming.items():
            ids = np.concatenate([fin for _, fin in parts])
            pos = np.concatenate([np.full(len(fin), q) for q, fin in parts])
            rest = np.array([[r for r in range(k) if r != q] for q in pos], dtype=np.int64)
            stacked = None
            if pregather:
                stacked = _stack(tables[k], parts)
            batches.append((k, ids, pos, rest, parts, stacked))
        weight = 1.0 / max(n_in, n_out, 1)
        plan.append((i, groups, batches, weight))
    return plan


def _run_pass(plan, theta, tables, msg):
    """One SRMP pass: receive from incoming factors, send shares of the belief to outgoing."""
    for i, groups, batches, weight in plan:
        for k, ids, pos, rest, parts, stacked in batches:
            if stacked is None:
                stacked = _stack(tables[k], parts)
            beliefs = {j + 1: -msg[k][ids, rest[:, j]].astype(np.float32) for j in range(k - 1)}
            msg[k][ids, pos] = min_to_axis(stacked, beliefs, 0)
        bi = theta[i].copy()
        for k, q, f, _fout in groups:
            bi += msg[k][f, q].sum(axis=0)
        for k, q, _f, fout in groups:
            if len(fout):
                msg[k][fout, q] -= weight * bi


def solve_srmp(
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
    decode_every: int = 5,
) -> SolveResult:
    """SRMP: forward and backward passes of reweighted factor-to-variable messages.

    One iteration is a forward and a backward pass over the variables; after each pass every
    reparametrised factor has minimum 0, so the bound is the sum of the variables' minima.
    """
    clock = Clock(time_limit)
    n, lab = mrf.unaries.shape
    big = forbidden_cost(mrf)
    theta = np.minimum(mrf.unaries, big)
    scopes = {k: g.scopes for k, g in mrf.groups.items()}
    tables = {k: np.minimum(g.tables, np.float32(big)) for k, g in mrf.groups.items()}
    msg = {k: np.zeros((len(g), k, lab)) for k, g in mrf.groups.items()}
    incidence = _incidence(scopes, n)
    order = np.arange(n)
    pregather = sum(2 * (k - 1) * t.nbytes for k, t in tables.items()) <= PREGATHER_BYTES
    forward = _pass_plan(scopes, incidence, order, tables, pregather)
    backward = _pass_plan(scopes, incidence, order[::-1], tables, pregather)

    primal = PrimalTracker(mrf, local_search=local_search)
    best_lb = -np.inf
    hist_e, hist_lb = [], []
    status, it = 1, 0
    while it < max_iter:
        it += 1
        _run_pass(forward, theta, tables, msg)
        _run_pass(backward, theta, tables, msg)
        full = theta.copy()
        for k, sc in scopes.items():
            for q in range(k):
                np.add.at(full, sc[:, q], msg[k][:, q])
        lb = float(full.min(axis=1).sum())
        best_lb = max(best_lb, lb)
        primal.offer(full.argmin(axis=1))
        if it <= 3 or it % decode_every == 0:
            primal.offer(_sequential_decode(full, scopes, tables, msg, incidence, big))
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

    lower, mm = _dual_certificate(theta, scopes, tables, msg, n, lab)
    if status == 0 and not gap_closed(primal.energy, lower, tol, atol + rounding_slack(big)):
        status = 2
    return make_result(
        x=primal.x,
        energy=primal.energy,
        lower_bound=lower,
        n_iter=it,
        status=status,
        time=clock.elapsed,
        min_marginals=finish_min_marginals(mm, mrf, big),
        history={"energy": np.asarray(hist_e), "lower_bound": np.asarray(hist_lb)},
        method="srmp",
    )
