"""Dual decomposition into factor trees with projected subgradient (Komodakis et al. 2011)."""

from __future__ import annotations

import numpy as np

from medseg.mrf._forest import build_forest, copy_min_marginals, decode, upward
from medseg.mrf._kernels import forbidden_cost, working_tables
from medseg.mrf._model import MRF
from medseg.mrf._primal import Clock, PrimalTracker, certified_result, gap_closed
from medseg.mrf._result import SolveResult
from medseg.mrf._trees import factor_tree_cover

__all__ = ["solve_subgradient", "tree_cover_of"]


def tree_cover_of(mrf: MRF) -> dict[int, np.ndarray]:
    """Tree index of every factor, by order (greedy first-fit cover over all orders)."""
    orders = sorted(mrf.groups)
    flat = [s for k in orders for s in mrf.groups[k].scopes.tolist()]
    tree = factor_tree_cover(flat, mrf.n_variables)
    out, offset = {}, 0
    for k in orders:
        c = len(mrf.groups[k])
        out[k] = tree[offset : offset + c]
        offset += c
    return out


def solve_subgradient(
    mrf: MRF,
    *,
    max_iter: int,
    tol: float,
    atol: float,
    time_limit: float | None,
    patience: int,
    min_step_scale: float,
    initial_scale: float = 1.0,
    decode_every: int = 5,
    local_search: bool,
    progress,
) -> SolveResult:
    """Projected-subgradient ascent on the factor-tree dual; see :func:`medseg.mrf.solve`."""
    clock = Clock(time_limit)
    n, lab = mrf.unaries.shape
    big = forbidden_cost(mrf)
    theta = np.minimum(mrf.unaries, big)
    scopes = {k: g.scopes for k, g in mrf.groups.items()}
    forest = build_forest(scopes, tree_cover_of(mrf), n)
    tables = {k: working_tables(g.tables, forest.perm[k], big) for k, g in mrf.groups.items()}

    cv = forest.copy_var
    count = forest.copy_count
    isolated = count == 0
    iso_lb = float(theta[isolated].min(axis=1).sum())
    share = theta[cv] / count[cv][:, None]
    lam = np.zeros((forest.n_copies, lab))
    rows = np.arange(forest.n_copies)

    primal = PrimalTracker(mrf, local_search=local_search)
    best_lb, best_lam = -np.inf, lam.copy()
    scale, since = initial_scale, 0
    hist_e, hist_lb = [], []
    status, it = 1, 0
    while it < max_iter:
        it += 1
        bel, msgs = upward(forest, tables, share + lam)
        dual = float(bel[forest.roots].min(axis=1).sum(dtype=np.float64)) + iso_lb
        if dual > best_lb:
            best_lb, best_lam, since = dual, lam.copy(), 0
        else:
            since += 1
        xc = decode(forest, tables, bel)
        votes = np.zeros((n, lab))
        np.add.at(votes, (cv, xc), 1.0)
        # primal: each variable takes the label most of its copies chose
        cand = votes.argmax(axis=1)
        cand[isolated] = theta[isolated].argmin(axis=1)
        primal.offer(cand)
        if it <= 3 or it % decode_every == 0:
            # the labelling minimising the summed min-marginals of the copies
            mmc = copy_min_marginals(forest, tables, bel, msgs)
            summed = theta.copy()
            summed[~isolated] = 0.0
            np.add.at(summed, cv, mmc - mmc.min(axis=1, keepdims=True))
            primal.offer(summed.argmin(axis=1))
        hist_e.append(primal.energy)
        hist_lb.append(best_lb)
        progress.update(1)
        if gap_closed(primal.energy, best_lb, tol, atol):
            status = 0
            break
        g = -votes[cv] / count[cv][:, None]
        g[rows, xc] += 1.0
        gnorm2 = float((g * g).sum())
        if gnorm2 == 0.0:  # every copy agrees: the trees' labelling is optimal
            best_lb = max(best_lb, dual)
            status = 0
            break
        # Polyak step towards the best primal energy, an upper bound on the dual optimum;
        # the scale halves whenever the dual has not improved for `patience` steps.
        step = scale * (primal.energy - dual) / gnorm2
        lam += step * g
        if since >= patience:
            scale *= 0.5
            since = 0
            if scale < min_step_scale:
                status = 2
                break
        if clock.out_of_time():
            status = 3
            break

    # certificate: the dual at the best multipliers, in float64
    bel, msgs = upward(forest, tables, share + best_lam, dtype=np.float64)
    lower = float(bel[forest.roots].min(axis=1).sum()) + iso_lb
    mmc = copy_min_marginals(forest, tables, bel, msgs)
    mm = np.zeros((n, lab))
    np.add.at(mm, cv, mmc - mmc.min(axis=1, keepdims=True))
    mm[isolated] = theta[isolated] - theta[isolated].min(axis=1, keepdims=True)
    mm += lower
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
        method="subgradient",
        n_trees=forest.n_trees,
    )
