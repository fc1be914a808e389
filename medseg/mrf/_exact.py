"""Reference solvers: exhaustive search and the local-polytope ILP / LP (HiGHS)."""

from __future__ import annotations

import time

import numpy as np
from scipy import sparse
from scipy.optimize import Bounds, LinearConstraint, milp

from medseg.errors import ResourceLimitError
from medseg.mrf._model import MRF, check_memory
from medseg.mrf._result import SolveResult, make_result

__all__ = ["exhaustive_search", "solve_ilp", "estimate_ilp_bytes"]


def exhaustive_search(mrf: MRF, *, max_labellings: int = 10**7) -> SolveResult:
    """Exact minimum and exact min-marginals by enumerating every labelling.

    Parameters
    ----------
    mrf : MRF
    max_labellings : int, default 10**7
        Refuse (``ResourceLimitError``) problems with more labellings than this.

    Returns
    -------
    SolveResult
        ``lower_bound == energy`` (the exact minimum), ``min_marginals[i, l] =
        min {E(x) : x_i = l}`` exactly.
    """
    t0 = time.perf_counter()
    n_total = int(np.prod(mrf.n_labels.astype(object)))
    if n_total > max_labellings:
        raise ResourceLimitError(
            f"exhaustive search over {n_total} labellings exceeds max_labellings="
            f"{max_labellings}; use solve() or solve_ilp() for a problem of this size"
        )
    n, lab = mrf.unaries.shape
    mm = np.full((n, lab), np.inf)
    best_x, best_e = None, np.inf
    step = max(1, 2**20 // max(n, 1))
    for start in range(0, n_total, step):
        flat = np.arange(start, min(n_total, start + step))
        x = np.stack(np.unravel_index(flat, tuple(mrf.n_labels.tolist())), axis=1)
        e = mrf._energies(x)
        j = int(np.argmin(e))
        if e[j] < best_e:
            best_e, best_x = float(e[j]), x[j].copy()
        for i in range(n):
            np.minimum.at(mm[i], x[:, i], e)
    return make_result(
        x=best_x,
        energy=best_e,
        lower_bound=best_e,
        n_iter=n_total,
        status=0,
        time=time.perf_counter() - t0,
        min_marginals=mm,
        method="exhaustive",
    )


def _ilp_sizes(mrf: MRF) -> tuple[int, int, int]:
    lab = mrf.max_labels
    n_cols = mrf.n_variables * lab + sum(len(g) * lab**k for k, g in mrf.groups.items())
    n_rows = mrf.n_variables + sum(len(g) * k * lab for k, g in mrf.groups.items())
    nnz = mrf.n_variables * lab + sum(len(g) * lab**k * (k + 1) for k, g in mrf.groups.items())
    return n_cols, n_rows, nnz


def estimate_ilp_bytes(mrf: MRF) -> int:
    """Rough memory of :func:`solve_ilp` (the constraint matrix and HiGHS's copies of it)."""
    n_cols, n_rows, nnz = _ilp_sizes(mrf)
    return int(nnz * 16 * 4 + (n_cols + n_rows) * 8 * 12)


def _local_polytope(mrf: MRF):
    """Cost vector, bounds and equality constraints of the local-polytope program."""
    n, lab = mrf.unaries.shape
    costs = [mrf.unaries.ravel()]
    rows, cols = [np.arange(n).repeat(lab)], [np.arange(n * lab)]
    vals = [np.ones(n * lab)]
    col0, row0 = n * lab, n
    for k, g in mrf.groups.items():
        c = len(g)
        size = lab**k
        costs.append(g.tables.reshape(-1).astype(np.float64))
        cfg = np.arange(size)
        digits = np.stack(np.unravel_index(cfg, (lab,) * k))  # (k, size)
        colf = col0 + np.arange(c * size)
        block = row0 + (np.arange(c)[:, None] * k) * lab
        for q in range(k):
            # sum over the factor's configurations with x_q = l, minus mu_{scope_q}(l), = 0
            rows += [(block + q * lab + digits[q][None, :]).ravel()]
            cols += [colf]
            vals += [np.ones(c * size)]
            rows += [(block + q * lab + np.arange(lab)[None, :]).ravel()]
            cols += [(g.scopes[:, q][:, None] * lab + np.arange(lab)).ravel()]
            vals += [-np.ones(c * lab)]
        col0 += c * size
        row0 += c * k * lab
    cost = np.concatenate(costs)
    upper = np.where(np.isinf(cost), 0.0, 1.0)
    cost = np.where(np.isinf(cost), 0.0, cost)
    a = sparse.csr_array(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(row0, col0),
    )
    rhs = np.zeros(row0)
    rhs[:n] = 1.0
    return cost, upper, a, rhs


def _is_integral(x: np.ndarray | None) -> bool:
    return x is not None and bool(np.allclose(x, np.round(x), atol=1e-6))


def solve_ilp(
    mrf: MRF,
    *,
    relaxation: bool = False,
    time_limit: float | None = None,
    max_bytes: int | None = None,
) -> SolveResult:
    """Exact minimum (integer program) or local-polytope LP bound, by HiGHS.

    Variables ``mu_i(l)`` and ``mu_f(x_f)`` with ``sum_l mu_i(l) = 1`` and, for every factor
    ``f``, position ``q`` and label ``l``, ``sum_{x_f : x_q = l} mu_f(x_f) = mu_{f_q}(l)``.
    Forbidden entries have their variable fixed to 0. The LP is solved first; when its
    optimum is integral it is returned as the ILP optimum, otherwise the ILP is solved.

    Parameters
    ----------
    mrf : MRF
    relaxation : bool, default False
        Solve the LP relaxation instead (``integrality = 0``): ``lower_bound`` is the
        local-polytope bound that dual decomposition can at best reach, and ``x`` the
        argmax of ``mu_i``.
    time_limit : float, optional
        Seconds given to HiGHS (LP and ILP together; HiGHS may overrun it in presolve);
        reaching it is status 3 (``lower_bound`` is then HiGHS's dual bound and ``x`` its
        best incumbent, if any).
    max_bytes : int, optional
        Memory budget checked against :func:`estimate_ilp_bytes`.

    Returns
    -------
    SolveResult
        Also ``highs_status`` and ``highs_message`` from :func:`scipy.optimize.milp`.
    """
    t0 = time.perf_counter()
    check_memory(estimate_ilp_bytes(mrf), max_bytes, "solve_ilp")
    cost, upper, a, rhs = _local_polytope(mrf)
    options = {"disp": False}
    if time_limit is not None:
        options["time_limit"] = float(time_limit)

    def run(integral: bool):
        return milp(
            cost,
            integrality=np.ones_like(cost) if integral else np.zeros_like(cost),
            bounds=Bounds(0.0, upper),
            constraints=LinearConstraint(a, rhs, rhs),
            options=options,
        )

    # the LP first: when its optimum is integral it is the ILP optimum (HiGHS's MIP presolve
    # alone can take minutes on models that the LP settles in seconds)
    res = run(False)
    if not relaxation and not (res.status == 0 and _is_integral(res.x)):
        if time_limit is not None:
            options["time_limit"] = max(1e-3, float(time_limit) - (time.perf_counter() - t0))
        res = run(True)
    n, lab = mrf.unaries.shape
    if res.x is not None:
        mu = res.x[: n * lab].reshape(n, lab)
        x = mu.argmax(axis=1)
        energy = float(mrf._energies(x[None])[0])
    else:
        x, energy = mrf.unaries.argmin(axis=1), np.inf
    if res.status == 0:
        lower, status = float(res.fun), 0
    else:
        bound = getattr(res, "mip_dual_bound", None)
        lower = float(bound) if bound is not None and np.isfinite(bound) else -np.inf
        status = 3 if res.status == 1 else 4
    return make_result(
        x=x,
        energy=energy,
        lower_bound=lower,
        n_iter=int(getattr(res, "mip_node_count", 0) or 0),
        status=status,
        time=time.perf_counter() - t0,
        min_marginals=None,
        method="lp" if relaxation else "ilp",
        highs_status=int(res.status),
        highs_message=str(res.message),
        integral=bool(res.x is not None and _is_integral(res.x)),
    )
