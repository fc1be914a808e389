"""``solve``: minimise an MRF energy by dual decomposition, with a certified lower bound."""

from __future__ import annotations

from numbers import Integral, Real

from tqdm.auto import tqdm

from medseg.errors import ProblemDefinitionError
from medseg.mrf._kernels import CHUNK_BYTES
from medseg.mrf._model import MRF, check_memory
from medseg.mrf._mplp import solve_mplp
from medseg.mrf._result import SolveResult
from medseg.mrf._srmp import solve_srmp
from medseg.mrf._subgradient import solve_subgradient
from medseg.progress import show_progress

__all__ = ["solve", "estimate_solver_bytes", "METHODS"]

METHODS = ("srmp", "mplp", "subgradient")


def estimate_solver_bytes(mrf: MRF, method: str = "srmp") -> int:
    """Peak memory (bytes) :func:`solve` is expected to allocate for ``mrf``.

    The working copy of the factor tables (float32) dominates; per-copy and per-factor
    message arrays (float64) and the chunked temporaries come on top.
    """
    lab = mrf.max_labels
    tables = sum(len(g) * lab**k * 4 for k, g in mrf.groups.items())
    incidences = sum(len(g) * k for k, g in mrf.groups.items()) + mrf.n_variables
    per_copy = (10 if method == "subgradient" else 4) * incidences * lab * 8
    return int(tables + per_copy + 8 * CHUNK_BYTES)


def _solve_iv(mrf, method, max_iter, tol, atol, time_limit, patience):
    if not isinstance(mrf, MRF):
        raise ProblemDefinitionError(
            f"`mrf` must be a medseg.mrf.MRF (build one with MRF(...) or MRF.from_triplets); "
            f"got {type(mrf).__name__}"
        )
    if method not in METHODS:
        raise ProblemDefinitionError(f"`method` must be one of {METHODS}; got {method!r}")
    if not isinstance(max_iter, Integral) or max_iter < 1:
        raise ProblemDefinitionError(f"`max_iter` must be a positive integer; got {max_iter!r}")
    if not isinstance(patience, Integral) or patience < 1:
        raise ProblemDefinitionError(f"`patience` must be a positive integer; got {patience!r}")
    for name, value in (("tol", tol), ("atol", atol)):
        if not isinstance(value, Real) or not value >= 0:
            raise ProblemDefinitionError(f"`{name}` must be a number >= 0; got {value!r}")
    if time_limit is not None and (not isinstance(time_limit, Real) or not time_limit > 0):
        raise ProblemDefinitionError(
            f"`time_limit` must be a positive number of seconds or None; got {time_limit!r}"
        )


def solve(
    mrf: MRF,
    *,
    method: str = "srmp",
    max_iter: int = 500,
    tol: float = 1e-3,
    atol: float = 1e-9,
    time_limit: float | None = None,
    patience: int = 20,
    local_search: bool = True,
    max_bytes: int | None = None,
    progress: bool = False,
    warm_start: SolveResult | None = None,
) -> SolveResult:
    """Minimise the energy of a higher-order MRF by dual decomposition.

    Parameters
    ----------
    mrf : MRF
    method : {"srmp", "mplp", "subgradient"}, default "srmp"
        ``"subgradient"``: the paper's reference. The factors are covered greedily by few
        factor trees (each factor in exactly one tree, no cycle through factors), every
        variable's unary is split evenly among its copies, each tree is solved exactly by
        batched min-sum belief propagation, and the multipliers tying the copies follow the
        projected subgradient with a Polyak step aimed at the best primal energy (its scale
        halves after ``patience`` iterations without a better dual).
        ``"mplp"``: block-coordinate dual ascent on the same local-polytope dual, with the
        factors as blocks (MPLP updates). Factors are coloured so that no two in a colour
        share a variable; one iteration is a sweep over the colours, each colour one batched
        update. The dual never decreases, but it can stall at a point below the LP bound.
        ``"srmp"``: sequential reweighted message passing (Kolmogorov 2015), the
        higher-order generalisation of TRW-S: forward and backward passes over the
        variables, each receiving min-marginal messages from the factors that reach back
        and sending them an equal share of its belief. Also monotone, with better fixed
        points than MPLP; the fastest of the three here (see benchmarks/bench_mrf.py).
        When its bound stalls (``patience``), a burst of 100 projected-subgradient steps on
        the same dual moves it off the stall point before message passing resumes (at
        most 3 bursts that bring no gain, then status 2).
    max_iter : int, default 500
        Subgradient steps, MPLP sweeps, or SRMP forward+backward pass pairs.
    tol : float, default 1e-3
        Stop when ``energy - lower_bound <= max(tol * |energy|, atol)``.
    atol : float, default 1e-9
    time_limit : float, optional
        Seconds; reaching it is status 3.
    patience : int, default 20
        Subgradient: steps without a better dual before the step scale halves (status 2
        once it falls below 1e-3). MPLP / SRMP: iterations over which the bound must gain more than
        ``tol / 100`` of the energy, else status 2.
    local_search : bool, default True
        Polish every improving primal labelling with iterated conditional modes.
    max_bytes : int, optional
        Memory budget; default :data:`medseg.mrf.DEFAULT_MAX_BYTES`. Checked against
        :func:`estimate_solver_bytes` before anything is allocated.
    progress : bool, default False
        Show a tqdm bar of the iterations (only on a terminal).
    warm_start : SolveResult, optional
        An earlier MPLP or SRMP result on an MRF with the same factors (scopes and label
        counts; the unaries and tables may differ): its ``multipliers`` start the dual
        instead of zeros. Any multipliers give a valid bound, so this only changes how fast
        the bound and the labelling improve: a solve of the same factors with other unaries
        (the segmenter's further hypotheses) needs far fewer iterations from there.

    Returns
    -------
    SolveResult
        ``x`` (N,), ``energy``, ``lower_bound`` (recomputed in float64 at the end, a
        certified bound on the minimum), ``gap``, ``n_iter``, ``status``, ``success``,
        ``message``, ``time``, ``min_marginals`` (N, L_max), ``history``; see
        :class:`SolveResult` for the status codes.

    Raises
    ------
    ProblemDefinitionError
        Bad options.
    ResourceLimitError
        The estimated memory exceeds ``max_bytes``.

    Notes
    -----
    The working copy of the tables is float32; the loop's bounds are float32 sums, the
    returned ``lower_bound`` and ``min_marginals`` are exact float64 values of the dual at the
    final (MPLP, SRMP) or best (subgradient) multipliers. Forbidden (``+inf``) entries are replaced
    inside the solver by a finite cost larger than any feasible energy.

    References
    ----------
    N. Komodakis, N. Paragios, G. Tziritas, "MRF energy minimization and beyond via dual
    decomposition", IEEE TPAMI 33(3), 2011. doi:10.1109/TPAMI.2010.108

    A. Globerson, T. Jaakkola, "Fixing max-product: convergent message passing algorithms
    for MAP LP-relaxations", NIPS 2007.

    V. Kolmogorov, "A new look at reweighted message passing", IEEE TPAMI 37(5), 2015.
    doi:10.1109/TPAMI.2014.2363465

    D. Sontag, T. Meltzer, A. Globerson, T. Jaakkola, Y. Weiss, "Tightening LP relaxations
    for MAP using message passing", UAI 2008 (the cluster form of the MPLP update).

    Examples
    --------
    >>> import numpy as np
    >>> from medseg.mrf import MRF, solve
    >>> rng = np.random.default_rng(0)
    >>> mrf = MRF.from_triplets(rng.random((4, 3)), [[0, 1, 2], [1, 2, 3]],
    ...                         rng.random((2, 3, 3, 3)))
    >>> res = solve(mrf, tol=1e-9)
    >>> bool(res.lower_bound <= res.energy + 1e-9)
    True
    """
    _solve_iv(mrf, method, max_iter, tol, atol, time_limit, patience)
    warm = _warm_multipliers(mrf, method, warm_start)
    check_memory(estimate_solver_bytes(mrf, method), max_bytes, f"solve(method={method!r})")
    with tqdm(
        total=max_iter, desc=f"MRF {method}", disable=not (progress and show_progress())
    ) as bar:
        if method == "subgradient":
            return solve_subgradient(
                mrf,
                max_iter=max_iter,
                tol=tol,
                atol=atol,
                time_limit=time_limit,
                patience=patience,
                min_step_scale=1e-3,
                local_search=local_search,
                progress=bar,
            )
        solver = solve_mplp if method == "mplp" else solve_srmp
        return solver(
            mrf,
            max_iter=max_iter,
            tol=tol,
            atol=atol,
            time_limit=time_limit,
            patience=patience,
            stall_tol=tol / 100.0,
            local_search=local_search,
            progress=bar,
            warm_start=warm,
        )


def _warm_multipliers(mrf: MRF, method: str, warm_start) -> dict | None:
    """The multipliers of ``warm_start``, checked against ``mrf``'s factors."""
    if warm_start is None:
        return None
    if method == "subgradient":
        raise ProblemDefinitionError(
            "`warm_start` is supported by method='mplp' and 'srmp', not 'subgradient'"
        )
    multipliers = warm_start.get("multipliers") if isinstance(warm_start, dict) else None
    if multipliers is None:
        raise ProblemDefinitionError(
            "`warm_start` must be the SolveResult of an earlier solve with method='mplp' or "
            "'srmp' (it carries `multipliers`)"
        )
    for k, g in mrf.groups.items():
        expected = (len(g), k, mrf.max_labels)
        got = getattr(multipliers.get(k), "shape", None)
        if got != expected:
            raise ProblemDefinitionError(
                f"`warm_start` does not fit this MRF: multipliers of its order-{k} factors "
                f"have shape {got}, expected {expected} (same factors and label counts)"
            )
    if set(multipliers) != set(mrf.groups):
        raise ProblemDefinitionError(
            "`warm_start` does not fit this MRF: it has factors of other orders"
        )
    return multipliers
