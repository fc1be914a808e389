"""Third-order graph matching by dual decomposition: under one-to-one constraints
(:func:`solve_matching`), or many-to-one (:func:`solve_many_to_one`).

The energy (Zeng et al., CVPR 2010, Eq. 3) over boolean correspondence variables is written
here with one label per source point: ``x_i`` is one of the point's ``K`` candidate targets,
or "unmatched" (label ``K``):

    E(x) = sum_i theta_i(x_i) + sum_c theta_c(x_i, x_j, x_k),

subject to no target being used twice. It is split into

* a linear subproblem that sees the one-to-one constraints and a share of the singleton
  costs: a sparse rectangular assignment, solved exactly
  (``scipy.sparse.csgraph.min_weight_full_bipartite_matching``);
* one local subproblem per third-order clique, solved exactly by enumerating its
  ``(K + 1)^3`` label combinations, vectorised over the cliques.

The shares of the singleton costs are the dual variables; projected subgradient steps (the
projection keeps their sum over the subproblems equal to ``theta_i``) raise the lower bound
(sum of the subproblem minima). Each iterate of the linear subproblem is feasible, and the
best of them is returned with its energy and the bound.

Without the one-to-one constraints (:func:`solve_many_to_one`, the dense stage) the energy
is a third-order MRF, and its LP dual is raised by block-coordinate ascent instead of
subgradient steps: MPLP updates (Globerson & Jaakkola 2007; Sontag, Globerson & Jaakkola
2011) of one clique at a time, all the cliques of a colour class (no shared point) at once.
Each update cannot lower the bound, and there is no step size to tune.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike
from scipy.optimize import linear_sum_assignment
from scipy.sparse.csgraph import min_weight_full_bipartite_matching
from tqdm.auto import tqdm

from medseg.errors import ProblemDefinitionError

__all__ = [
    "MatchingProblem",
    "SolveResult",
    "solve_matching",
    "solve_many_to_one",
    "matching_energy",
]


@dataclass
class MatchingProblem:
    """A third-order matching problem on plain arrays.

    Parameters
    ----------
    unary : (N, K) float array
        ``theta_i`` of each source point's candidates; ``inf`` marks a padded (absent)
        candidate.
    candidates : (N, K) int array
        Target index of each candidate, in ``[0, n_targets)``; unique within a row
        (padding may repeat but must have ``inf`` cost).
    cliques : (T, 3) int array
        Source point triplets.
    clique_costs : (T, K, K, K) float array
        ``theta_c`` of every label combination of each clique.
    n_targets : int
        Number of target points.
    unmatched_cost : float
        Singleton cost of leaving a source point unmatched (label ``K``).
    unmatched_clique_cost : float
        Clique cost of any combination in which a point is unmatched.
    """

    unary: np.ndarray
    candidates: np.ndarray
    cliques: np.ndarray
    clique_costs: np.ndarray
    n_targets: int
    unmatched_cost: float
    unmatched_clique_cost: float


@dataclass
class SolveResult:
    """Outcome of :func:`solve_matching` (``scipy.optimize.OptimizeResult``-like).

    Attributes
    ----------
    x : (N,) int array
        Chosen candidate column per source point, ``K`` for unmatched.
    targets : (N,) int array
        Matched target index per source point, -1 for unmatched.
    energy : float
        ``E(x)`` of the returned labelling.
    lower_bound : float
        Best dual bound: no labelling satisfying the constraints has a lower energy.
    gap : float
        ``(energy - lower_bound) / max(|energy|, 1e-12)``.
    n_iter : int
    success : bool
        Whether the gap fell below ``tol``.
    status : int
        0: gap below ``tol``; 1: iteration limit reached.
    message : str
    history : dict
        ``energy`` and ``lower_bound`` per iteration.
    """

    x: np.ndarray
    targets: np.ndarray
    energy: float
    lower_bound: float
    gap: float
    n_iter: int
    success: bool
    status: int
    message: str
    history: dict = field(default_factory=dict)


def _solve_iv(problem: MatchingProblem):
    unary = np.asarray(problem.unary, float)
    cand = np.asarray(problem.candidates)
    cliques = np.asarray(problem.cliques)
    costs = np.asarray(problem.clique_costs, float)
    if unary.ndim != 2 or unary.shape != cand.shape or unary.shape[0] == 0:
        raise ProblemDefinitionError(
            f"unary and candidates must be (N, K) arrays of the same shape, got "
            f"{unary.shape} and {cand.shape}."
        )
    n, k = unary.shape
    if np.any(np.isnan(unary)) or np.any(unary == -np.inf):
        raise ProblemDefinitionError("unary costs must be finite or +inf (padding).")
    if not np.issubdtype(cand.dtype, np.integer) or cand.min() < 0:
        raise ProblemDefinitionError("candidates must be non-negative integers.")
    if cand.max() >= problem.n_targets:
        raise ProblemDefinitionError(
            f"candidates must be below n_targets={problem.n_targets}, got {cand.max()}."
        )
    if cliques.size == 0:
        cliques = np.zeros((0, 3), dtype=np.int64)
        costs = np.zeros((0, k, k, k))
    if cliques.ndim != 2 or cliques.shape[1] != 3 or cliques.min() < 0 or cliques.max() >= n:
        raise ProblemDefinitionError("cliques must be a (T, 3) array of source indices < N.")
    if costs.shape != (len(cliques), k, k, k) or not np.all(np.isfinite(costs)):
        raise ProblemDefinitionError(
            f"clique_costs must be a finite ({len(cliques)}, {k}, {k}, {k}) array, "
            f"got {costs.shape}."
        )
    for name in ("unmatched_cost", "unmatched_clique_cost"):
        if not np.isfinite(getattr(problem, name)):
            raise ProblemDefinitionError(f"{name} must be finite.")
    return unary, cand.astype(np.int64), cliques.astype(np.int64), costs


def _extend(unary, costs, problem):
    """Append the unmatched label K to the unary and clique tables."""
    n, k = unary.shape
    u = np.concatenate([unary, np.full((n, 1), float(problem.unmatched_cost))], axis=1)
    c = np.full((len(costs), k + 1, k + 1, k + 1), float(problem.unmatched_clique_cost))
    c[:, :k, :k, :k] = costs
    return u, c


def _energy(u: np.ndarray, c: np.ndarray, cliques: np.ndarray, x: np.ndarray) -> float:
    e = u[np.arange(len(x)), x].sum()
    if len(cliques):
        e += c[np.arange(len(cliques)), x[cliques[:, 0]], x[cliques[:, 1]], x[cliques[:, 2]]].sum()
    return float(e)


def matching_energy(problem: MatchingProblem, x: ArrayLike) -> float:
    """Energy ``E(x)`` of a labelling (column per source point, ``K`` = unmatched)."""
    unary, _, cliques, costs = _solve_iv(problem)
    u, c = _extend(unary, costs, problem)
    return _energy(u, c, cliques, np.asarray(x))


def _assignment(u_lin: np.ndarray, cand: np.ndarray, n_targets: int) -> tuple[np.ndarray, float]:
    """Min-cost one-to-one labelling of the linear subproblem; (labels, value).

    Small problems (the sparse stage) as a dense rectangular assignment over the targets
    some candidate names plus one "unmatched" column per point
    (:func:`scipy.optimize.linear_sum_assignment`, about 10 times faster there), large ones
    as a sparse bipartite matching."""
    n, k1 = u_lin.shape
    k = k1 - 1
    valid = np.isfinite(u_lin[:, :k])
    named, col = np.unique(cand[valid], return_inverse=True)
    if n * (len(named) + n) <= 2_000_000:
        finite = np.abs(u_lin[np.isfinite(u_lin)])
        big = 2.0 * (finite.sum() + 1.0)  # above any labelling that avoids it
        w = np.full((n, len(named) + n), big)
        w[np.nonzero(valid)[0], col] = u_lin[:, :k][valid]
        w[np.arange(n), len(named) + np.arange(n)] = u_lin[:, k]
        _, col_of_row = linear_sum_assignment(w)
        labels = np.full(n, k, dtype=np.int64)
        matched = col_of_row < len(named)
        hit = (cand[matched] == named[col_of_row[matched]][:, None]) & valid[matched]
        labels[np.flatnonzero(matched)] = np.argmax(hit, axis=1)
        return labels, float(u_lin[np.arange(n), labels].sum())
    rows = np.concatenate([np.repeat(np.arange(n), k)[valid.ravel()], np.arange(n)])
    cols = np.concatenate([cand.ravel()[valid.ravel()], n_targets + np.arange(n)])
    vals = np.concatenate([u_lin[:, :k][valid], u_lin[:, k]])
    # a constant per row does not change the optimum; keep weights strictly positive
    shift = np.minimum(np.where(valid, u_lin[:, :k], np.inf).min(axis=1), u_lin[:, k]) - 1.0
    w = sp.csr_matrix((vals - shift[rows], (rows, cols)), shape=(n, n_targets + n))
    _, col_of_row = min_weight_full_bipartite_matching(w)
    labels = np.full(n, k, dtype=np.int64)
    matched = col_of_row < n_targets
    # map target back to its candidate column
    hit = cand[matched] == col_of_row[matched][:, None]
    hit &= valid[matched]
    labels[np.flatnonzero(matched)] = np.argmax(hit, axis=1)
    return labels, float(u_lin[np.arange(n), labels].sum())


_MESSAGES = {
    0: "duality gap below tol",
    1: "iteration limit reached",
    2: "the bound stopped rising",
}


def _result(x, cand, k1, energy, lower_bound, n_done, status, hist_e, hist_lb) -> SolveResult:
    """A solver's result: labels ``x`` (``k1 - 1`` is "no match") and their targets."""
    n, k = len(x), k1 - 1
    return SolveResult(
        x=x,
        targets=np.where(x < k, cand[np.arange(n), np.minimum(x, k - 1)], -1),
        energy=float(energy),
        lower_bound=float(lower_bound),
        gap=float((energy - lower_bound) / max(abs(energy), 1e-12)),
        n_iter=n_done,
        success=status == 0,
        status=status,
        message=_MESSAGES[status],
        history={"energy": np.asarray(hist_e), "lower_bound": np.asarray(hist_lb)},
    )


def solve_matching(
    problem: MatchingProblem,
    *,
    max_iter: int = 100,
    tol: float = 1e-3,
    step: float = 1.0,
    progress: bool = False,
) -> SolveResult:
    """Minimise a third-order matching energy under one-to-one constraints.

    Parameters
    ----------
    problem : MatchingProblem
    max_iter : int
        Subgradient iterations.
    tol : float
        Stop when the relative duality gap is below ``tol``.
    step : float
        Initial factor of the Polyak step ``step * (E_best - bound) / ||g||^2``; halved when
        the bound has not improved for 10 iterations.
    progress : bool
        Show a tqdm bar.

    Returns
    -------
    SolveResult

    References
    ----------
    .. [1] Komodakis, N., Paragios, N. & Tziritas, G. "MRF energy minimization and beyond
       via dual decomposition." IEEE TPAMI 33(3), 2011. doi:10.1109/TPAMI.2010.108
    .. [2] Zeng, Y., Wang, C., Wang, Y., Gu, X., Samaras, D. & Paragios, N. "Dense non-rigid
       surface registration using high-order graph matching." CVPR 2010.
       doi:10.1109/CVPR.2010.5540189
    """
    unary, cand, cliques, costs = _solve_iv(problem)
    u, c = _extend(unary, costs, problem)
    c0 = c
    n, k1 = u.shape
    t_count = len(cliques)
    deg = 1.0 + np.bincount(cliques.ravel(), minlength=n)
    # shares: linear subproblem gets u / deg, each clique slot the same (padding: inf stays
    # in the linear share only, cliques see a large finite cost instead)
    finite_u = np.where(np.isfinite(u), u, 0.0)
    share = finite_u / deg[:, None]
    u_lin = np.where(np.isfinite(u), share, np.inf)
    u_cl = share[cliques]  # (T, 3, K+1)
    pad = ~np.isfinite(u)
    big = 10.0 * (np.abs(c).max(initial=0.0) + np.abs(finite_u).max(initial=0.0) + 1.0)
    c = c.copy()
    if t_count and pad.any():
        for p in range(3):
            bad = pad[cliques[:, p]]  # (T, K+1)
            shape = [t_count, 1, 1, 1]
            shape[p + 1] = k1
            c += big * bad.reshape(shape)
    best_x, best_e, best_lb = None, np.inf, -np.inf
    hist_e, hist_lb = [], []
    stall, status, n_done = 0, 1, 0
    lr = step
    bar = tqdm(total=max_iter, disable=not progress, desc="dual decomposition", leave=False)
    for it in range(1, max_iter + 1):
        n_done = it
        x_lin, val_lin = _assignment(u_lin, cand, problem.n_targets)
        if t_count:
            tot = (
                c
                + u_cl[:, 0, :, None, None]
                + u_cl[:, 1, None, :, None]
                + u_cl[:, 2, None, None, :]
            )
            flat = tot.reshape(t_count, -1)
            arg = np.argmin(flat, axis=1)
            val_cl = flat[np.arange(t_count), arg].sum()
            x_cl = np.stack(np.unravel_index(arg, (k1, k1, k1)), axis=1)  # (T, 3)
        else:
            val_cl = 0.0
        lb = val_lin + val_cl
        e = _energy(u, c0, cliques, x_lin)
        if e < best_e:
            best_e, best_x = e, x_lin
        if not np.isfinite(best_lb) or lb > best_lb + 1e-9 * max(abs(best_lb), 1.0):
            best_lb, stall = lb, 0
        else:
            stall += 1
            if stall >= 10:
                lr, stall = lr / 2, 0
        hist_e.append(e)
        hist_lb.append(lb)
        bar.update(1)
        bar.set_postfix(energy=f"{best_e:.4g}", bound=f"{best_lb:.4g}")
        gap = (best_e - best_lb) / max(abs(best_e), 1e-12)
        if gap < tol or not t_count:
            status = 0
            break
        # subgradient: indicator of each slave minus their mean per variable
        ind_lin = np.zeros((n, k1))
        ind_lin[np.arange(n), x_lin] = 1.0
        ind_cl = np.zeros((t_count, 3, k1))
        ind_cl[np.arange(t_count)[:, None], np.arange(3)[None, :], x_cl] = 1.0
        mean = ind_lin.copy()
        np.add.at(mean, cliques.ravel(), ind_cl.reshape(-1, k1))
        mean /= deg[:, None]
        g_lin = ind_lin - mean
        g_cl = ind_cl - mean[cliques]
        norm2 = float((g_lin**2).sum() + (g_cl**2).sum())
        if norm2 == 0.0:  # all subproblems agree: the labelling is optimal
            best_lb = max(best_lb, lb)
            status = 0
            break
        alpha = lr * max(best_e - lb, 1e-6 * max(abs(best_e), 1.0)) / norm2
        u_lin = u_lin + alpha * g_lin
        u_cl = u_cl + alpha * g_cl
    bar.close()
    return _result(best_x, cand, k1, best_e, best_lb, n_done, status, hist_e, hist_lb)


def _colour_cliques(cliques: np.ndarray, n: int) -> np.ndarray:
    """Greedy colouring of the cliques: two cliques of one colour share no point."""
    used = [0] * n  # per point, bit mask of the colours of its cliques so far
    colour = np.empty(len(cliques), dtype=np.int64)
    for t, (i, j, k) in enumerate(cliques.tolist()):
        taken = used[i] | used[j] | used[k]
        c = (~taken & (taken + 1)).bit_length() - 1  # lowest free colour
        colour[t] = c
        used[i] |= 1 << c
        used[j] |= 1 << c
        used[k] |= 1 << c
    return colour


def _colour_points(cliques: np.ndarray, n: int) -> np.ndarray:
    """Greedy colouring of the points: two points of one colour share no clique."""
    nbrs = [[] for _ in range(n)]
    for i, j, k in cliques.tolist():
        nbrs[i] += (j, k)
        nbrs[j] += (i, k)
        nbrs[k] += (i, j)
    colour = np.full(n, -1, dtype=np.int64)
    col = colour.tolist()
    for v in range(n):
        taken = {col[w] for w in nbrs[v]}
        c = 0
        while c in taken:
            c += 1
        col[v] = c
    colour[:] = col
    return colour


def _icm(theta, c, cliques, x, colour, *, max_sweeps=10):
    """Iterated conditional modes from ``x``: each point in turn takes its best label given
    the others, the points of one colour at once (they share no clique). Never raises the
    energy."""
    x = x.copy()
    n = len(x)
    row = np.empty(n, dtype=np.int64)
    classes = []
    for k in range(int(colour.max()) + 1 if n else 0):
        pts = np.flatnonzero(colour == k)
        row[pts] = np.arange(len(pts))
        of = [np.flatnonzero(colour[cliques[:, q]] == k) for q in range(3)]
        classes.append((pts, of))
    for _ in range(max_sweeps):
        moved = 0
        for pts, of in classes:
            local = theta[pts].copy()
            for q, sel in enumerate(of):
                xs = x[cliques[sel]]
                index = [sel, xs[:, 0], xs[:, 1], xs[:, 2]]
                index[q + 1] = slice(None)
                vals = c[tuple(index)]  # (s, L): the clique's cost for every label of q
                np.add.at(local, row[cliques[sel, q]], vals)
            new = local.argmin(axis=1)
            keep = local[np.arange(len(pts)), x[pts]] <= local[np.arange(len(pts)), new]
            new = np.where(keep, x[pts], new)  # ties: stay
            moved += int((new != x[pts]).sum())
            x[pts] = new
        if not moved:
            break
    return x


def _min_marginals(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Min-marginals of (L, L, L, T) tables (cliques last, so that every reduction runs
    over contiguous rows) on each of their three label axes, each (L, T)."""
    m12 = m.min(axis=0)  # (L, L, T): over the first label
    return m.min(axis=(1, 2)), m12.min(axis=1), m12.min(axis=0)


def solve_many_to_one(
    problem: MatchingProblem,
    *,
    max_iter: int = 200,
    tol: float = 1e-3,
    patience: int = 10,
    polish_every: int = 25,
    progress: bool = False,
) -> SolveResult:
    """Minimise a third-order matching energy without the one-to-one constraints.

    Every source point takes one of its candidates, or "unmatched" (label ``K``); several
    points may take the same target. ``problem.n_targets`` only bounds the candidates.

    Parameters
    ----------
    problem : MatchingProblem
    max_iter : int
        Sweeps over all cliques.
    tol : float
        Stop when the relative duality gap is below ``tol``.
    patience : int
        Also stop when the bound rose by less than ``tol / 10`` (relative) over this many
        sweeps: the dual has converged, and the remaining gap is that of the relaxation.
    polish_every : int
        Every this many sweeps, and at the end, the decoded labelling is improved by
        iterated conditional modes (a point at a time takes its best label given the
        others) before its energy is compared with the best so far.
    progress : bool
        Show a tqdm bar.

    Returns
    -------
    SolveResult
        ``status`` 0: gap below ``tol``; 1: iteration limit; 2: the bound stopped rising.
        ``lower_bound`` is the exact dual value of the final multipliers.

    Notes
    -----
    Dual of the local-polytope relaxation: ``theta_i + sum_c lambda_ci`` on the points,
    ``theta_c - sum_i lambda_ci`` on the cliques, bound = the sum of their minima. The MPLP
    update of clique ``c`` sets, for each of its points, ``lambda_ci = mu_i / 3 - b_i``,
    where ``b_i`` is the point's reparametrised cost without ``c`` and ``mu_i`` the
    min-marginal of ``theta_c + b_j + b_k + b_i``: afterwards the clique's reparametrised
    minimum is 0 and its three points share its min-marginals. The labelling decoded after
    each sweep is each point's cheapest label (polished, see ``polish_every``).

    References
    ----------
    .. [1] Globerson, A. & Jaakkola, T. "Fixing max-product: convergent message passing
       algorithms for MAP LP-relaxations." NIPS 2007.
    .. [2] Sontag, D., Globerson, A. & Jaakkola, T. "Introduction to dual decomposition for
       inference." In Optimization for Machine Learning, MIT Press, 2011.
    """
    unary, cand, cliques, costs = _solve_iv(problem)
    u, c = _extend(unary, costs, problem)
    n, k1 = u.shape
    finite = np.isfinite(u)
    # padded candidates: a cost above any labelling that avoids them
    big = 10.0 * (np.abs(c).max(initial=0.0) * max(len(cliques), 1) + np.abs(u[finite]).sum() + 1)
    theta = np.where(finite, u, big)
    colour = _colour_cliques(cliques, n)
    order = np.argsort(colour, kind="stable")
    cl, col = cliques[order], colour[order]
    bounds = np.flatnonzero(np.r_[True, col[1:] != col[:-1], True]) if len(cl) else [0]
    # per colour class: tables (L, L, L, m) and multipliers (3, L, m), cliques last
    blocks = [
        (cl[s:e], np.ascontiguousarray(np.moveaxis(c[order[s:e]], 0, -1)), np.zeros((3, k1, e - s)))
        for s, e in zip(bounds[:-1], bounds[1:], strict=True)
    ]
    belief = theta.copy()  # theta_i + sum over its cliques of lambda_ci
    point_colour = _colour_points(cliques, n)
    best_x, best_e, best_lb = None, np.inf, -np.inf
    hist_e, hist_lb = [], []
    status, n_done = 1, 0
    bar = tqdm(total=max_iter, disable=not progress, desc="MPLP", leave=False)
    for it in range(1, max_iter + 1):
        n_done = it
        for sc, tab, lk in blocks:
            rest = np.stack([belief[sc[:, q]].T for q in range(3)]) - lk  # (3, L, m)
            m = tab + rest[0][:, None, None, :] + rest[1][None, :, None, :]
            m += rest[2][None, None, :, :]
            for q, mu in enumerate(_min_marginals(m)):
                lk[q] = mu / 3 - rest[q]
                belief[sc[:, q]] = mu.T / 3
        # every clique's reparametrised minimum is 0 after its update: the bound is
        lb = float(belief.min(axis=1).sum())
        x = belief.argmin(axis=1)
        if it % polish_every == 0:
            x = _icm(theta, c, cliques, x, point_colour)
        e = _energy(theta, c, cliques, x)
        if e < best_e:
            best_e, best_x = e, x
        best_lb = max(best_lb, lb)
        hist_e.append(e)
        hist_lb.append(lb)
        bar.update(1)
        if (best_e - best_lb) <= tol * max(abs(best_e), 1e-12) or not len(cl):
            status = 0
            break
        if it > patience and hist_lb[-1] - hist_lb[-1 - patience] <= 0.1 * tol * abs(best_e):
            status = 2
            break
    bar.close()
    polished = _icm(theta, c, cliques, best_x, point_colour)
    e = _energy(theta, c, cliques, polished)
    if e < best_e:
        best_e, best_x = e, polished
    # exact dual value of the final multipliers (clique minima are 0 up to rounding)
    best_lb = float(belief.min(axis=1).sum())
    for _, tab, lk in blocks:
        rep = tab - lk[0][:, None, None, :] - lk[1][None, :, None, :] - lk[2][None, None, :, :]
        best_lb += float(rep.min(axis=(0, 1, 2)).sum())
    return _result(best_x, cand, k1, best_e, best_lb, n_done, status, hist_e, hist_lb)
