"""Sequential reweighted message passing (SRMP, Kolmogorov 2015) for factors of order 2-3."""

from __future__ import annotations

import numpy as np

from medseg.mrf._decode import sequential_decode
from medseg.mrf._kernels import beliefs, chunks, forbidden_cost, min_to_axis
from medseg.mrf._model import MRF
from medseg.mrf._mplp import _dual_certificate, _incidence
from medseg.mrf._primal import Clock, PrimalTracker, certified_result, gap_closed
from medseg.mrf._result import SolveResult

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


def _factor_dual(theta, scopes, tables, msg):
    """Dual value, variable argmins (N,) and factor argmins {k: (C_k, k)} (float64)."""
    lab = theta.shape[1]
    belief = beliefs(theta, scopes, msg)
    value = float(belief.min(axis=1).sum())
    argmins = {}
    for k, sc in scopes.items():
        best = np.empty((len(sc), k), dtype=np.int64)
        for ch in chunks(len(sc), 2 * lab**k * 8):
            t = tables[k][ch].astype(np.float64)
            for q in range(k):
                shape = [t.shape[0]] + [1] * k
                shape[q + 1] = lab
                t -= msg[k][ch, q].reshape(shape)
            flat = t.reshape(len(t), -1)
            a = flat.argmin(axis=1)
            value += float(flat[np.arange(len(a)), a].sum())
            best[ch] = np.stack(np.unravel_index(a, (lab,) * k), axis=1)
        argmins[k] = best
    return value, belief.argmin(axis=1), argmins


def _subgradient_burst(theta, scopes, tables, msg, target, n_steps, scale=0.5):
    """Projected-subgradient steps on the same (factor-wise) dual, Polyak step to ``target``.

    Block-coordinate ascent can stall at points where no single block can improve the dual
    (weak tree agreement); subgradient steps move all messages at once and leave them.
    """
    for _ in range(n_steps):
        value, xv, xf = _factor_dual(theta, scopes, tables, msg)
        grads, norm2 = {}, 0.0
        for k, sc in scopes.items():
            g = np.zeros_like(msg[k])
            rows = np.arange(len(sc))
            for q in range(k):
                g[rows, q, xv[sc[:, q]]] += 1.0
                g[rows, q, xf[k][:, q]] -= 1.0
            grads[k] = g
            norm2 += float((g * g).sum())
        if norm2 == 0.0 or not target > value:
            return
        step = scale * (target - value) / norm2
        for k in msg:
            msg[k] += step * grads[k]


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
    warm_start: dict[int, np.ndarray] | None = None,
    decode_every: int = 5,
    burst_steps: int = 100,
    max_bursts: int = 3,
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
    if warm_start is None:
        msg = {k: np.zeros((len(g), k, lab)) for k, g in mrf.groups.items()}
    else:
        msg = {k: np.array(warm_start[k], dtype=np.float64) for k in mrf.groups}
    incidence = _incidence(scopes, n)
    order = np.arange(n)
    pregather = sum(2 * (k - 1) * t.nbytes for k, t in tables.items()) <= PREGATHER_BYTES
    forward = _pass_plan(scopes, incidence, order, tables, pregather)
    backward = _pass_plan(scopes, incidence, order[::-1], tables, pregather)

    primal = PrimalTracker(mrf, local_search=local_search)
    best_lb = -np.inf
    hist_e, hist_lb = [], []
    status, it = 1, 0
    last_burst, n_sub, bursts_left, lb_at_last_stall = 0, 0, max_bursts, None
    while it < max_iter:
        it += 1
        _run_pass(forward, theta, tables, msg)
        _run_pass(backward, theta, tables, msg)
        full = beliefs(theta, scopes, msg)
        lb = float(full.min(axis=1).sum())
        best_lb = max(best_lb, lb)
        primal.offer(full.argmin(axis=1))
        if it <= 3 or it % decode_every == 0:
            primal.offer(sequential_decode(full, scopes, tables, msg))
        hist_e.append(primal.energy)
        hist_lb.append(best_lb)
        progress.update(1)
        if gap_closed(primal.energy, best_lb, tol, atol):
            status = 0
            break
        if it - last_burst > patience and hist_lb[-1] - hist_lb[-1 - patience] <= stall_tol * max(
            abs(primal.energy), atol
        ):
            if bursts_left == 0 or not np.isfinite(primal.energy):
                status = 2
                break
            # stalled: a burst of subgradient steps, then message passing resumes
            _subgradient_burst(theta, scopes, tables, msg, primal.energy, burst_steps)
            n_sub += burst_steps
            last_burst = it
            gain = np.inf if lb_at_last_stall is None else best_lb - lb_at_last_stall
            if gain <= stall_tol * abs(primal.energy):  # the previous burst did not help
                bursts_left -= 1
            lb_at_last_stall = best_lb
        if clock.out_of_time():
            status = 3
            break

    lower, mm = _dual_certificate(theta, scopes, tables, msg, n, lab)
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
        method="srmp",
        n_subgradient_steps=n_sub,
        multipliers={k: m.copy() for k, m in msg.items()},
    )
