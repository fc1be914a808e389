"""The result object every solver of :mod:`medseg.mrf` returns."""

from __future__ import annotations

import numpy as np
from scipy.optimize import OptimizeResult

__all__ = ["SolveResult", "STATUS_MESSAGES", "relative_gap"]

#: Status codes shared by all solvers. ``success`` is ``status == 0``.
STATUS_MESSAGES = {
    0: "converged: the relative duality gap is within tolerance",
    1: "iteration limit reached before the gap closed",
    2: "stopped on stagnation: the lower bound stopped improving before the gap closed",
    3: "time limit reached before the gap closed",
    4: "no labelling of finite energy was found (the problem may be infeasible)",
}


class SolveResult(OptimizeResult):
    """Outcome of an MRF minimisation (a dict with attribute access).

    Attributes
    ----------
    x : (N,) int64 array
        Best labelling found.
    energy : float
        ``E(x)``.
    lower_bound : float
        Certified lower bound on the minimum energy (the dual value).
    gap : float
        Relative duality gap ``(energy - lower_bound) / |energy|`` (0 when both are 0).
    n_iter : int
        Iterations (subgradient steps or message-passing sweeps).
    success : bool
        ``status == 0``.
    status : int
        0 converged (gap <= tol), 1 iteration limit, 2 stagnation of the lower bound,
        3 time limit, 4 no finite-energy labelling found; see :data:`STATUS_MESSAGES`.
    message : str
    time : float
        Wall-clock seconds, setup included.
    min_marginals : (N, L_max) float64 array
        ``min_marginals[i, l]`` is a lower bound on ``min {E(x) : x_i = l}`` (exact for
        the exhaustive search); ``+inf`` beyond a variable's label count. The margin between
        the two smallest entries of row ``i`` is what it costs (at least, up to the gap) to
        move variable ``i`` to its second-best label: a confidence per landmark.
    history : dict of str -> (n_iter,) array, optional
        ``"energy"`` (best so far) and ``"lower_bound"`` (best so far) per iteration.

    Notes
    -----
    Solver-specific fields may be present; see ``.keys()``.
    """


def relative_gap(energy: float, lower_bound: float) -> float:
    """``(energy - lower_bound) / |energy|``; 0 for ``0/0`` and ``inf`` for ``x/0``."""
    diff = energy - lower_bound
    if not np.isfinite(energy):
        return float("inf")
    diff = max(diff, 0.0)
    if energy == 0:
        return 0.0 if diff == 0 else float("inf")
    return float(diff / abs(energy))


def make_result(
    *,
    x: np.ndarray,
    energy: float,
    lower_bound: float,
    n_iter: int,
    status: int,
    time: float,
    min_marginals: np.ndarray | None,
    **extra,
) -> SolveResult:
    if not np.isfinite(energy):
        status = 4
    res = SolveResult(
        x=np.asarray(x, dtype=np.int64),
        energy=float(energy),
        lower_bound=float(lower_bound),
        gap=relative_gap(float(energy), float(lower_bound)),
        n_iter=int(n_iter),
        status=int(status),
        success=status == 0,
        message=STATUS_MESSAGES[status],
        time=float(time),
        min_marginals=min_marginals,
    )
    res.update(extra)
    return res
