"""Graph cuts: the exact minimum of binary submodular energies, and Potts alpha-expansion.

A binary energy over nodes ``x_i in {0, 1}``,

    E(x) = sum_i U_i(x_i) + sum_(i,j) E_ij(x_i, x_j),

has an exact minimum in polynomial time when every pairwise term is *submodular*,
``E00 + E11 <= E01 + E10``: it is then the value of a minimum s-t cut in a graph with one
vertex per node (Kolmogorov & Zabih, "What energy functions can be minimized via graph
cuts?", IEEE TPAMI 26(2), 2004). Segmentation energies of the kind "data term plus boundary
length" are of this form, which is why a cut beats iterative local solvers there: it is the
global optimum, not a local one.

Several labels with a Potts boundary term ``w_ij [x_i != x_j]`` are NP-hard to minimise, but
alpha-expansion (Boykov, Veksler & Zabih, "Fast approximate energy minimization via graph
cuts", IEEE TPAMI 23(11), 2001) reaches a labelling within a factor 2 of the optimum (for
non-negative energies) by a sequence of binary moves, each solved exactly by a cut.

The max-flow is SciPy's (:func:`scipy.sparse.csgraph.maximum_flow`), which needs int32
capacities; :func:`binary_cut_bound` states how far the rounding can take the labelling from
the true minimum (about ``1e-9`` times the number of capacities times the largest one).

Conventions (one place): label 1 is the *source* side of the cut. The s->i capacity is paid
when node i takes label 0, the i->t capacity when it takes label 1, and the i->j capacity when
``x_i = 1, x_j = 0``. Among several minimum cuts the one with the fewest label-1 nodes (the
nodes reachable from the source in the residual graph) is returned, so ties and nodes without
any capacity get label 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy import sparse
from scipy.sparse.csgraph import breadth_first_order, maximum_flow

from medseg.errors import ParameterError

__all__ = [
    "minimize_binary",
    "binary_cut_bound",
    "binary_energy",
    "potts_expansion",
    "potts_energy",
    "grid_edges",
]

#: The largest integer capacity (and residual capacity, which can reach the sum of the two
#: directions of an edge) after scaling: a factor 2 inside int32. The scale is not capped
#: below this: Dinic's running time does not depend on the capacity values (30^3 grid:
#: 0.24 s at 2**30, 0.21 s at 2**20, while the rounding bound grows 1000-fold).
_CAPACITY_LIMIT = float(2**30)
_INT32_MAX = int(np.iinfo(np.int32).max)
#: Submodularity is checked up to this fraction of |E00| + |E01| + |E10| + |E11|
#: (the rounding of the caller's own arithmetic); a violation within it is set to zero.
_SUBMODULAR_RTOL = 1e-12
#: An expansion move is accepted when it lowers the energy by more than this fraction of the
#: energy's magnitude (float rounding of the energy sum; quantised cuts cannot cycle).
_ACCEPT_RTOL = 1e-12
# Max-flow algorithm: on a full 30x30x30 grid with random Potts terms (27,000 nodes,
# 78,300 edges, N(0, 1) unaries, U(0, 1) weights; 2 busy cores, SciPy 1.17.1) 'dinic' took
# 0.29 s and 'edmonds_karp' 50 s: the only other method SciPy offers.
_FLOW_METHOD = "dinic"


# ---------------------------------------------------------------------------------------
# input checks


def _float_array(value: ArrayLike, name: str, columns: int | None, rows: int | None) -> np.ndarray:
    """``value`` as float64 of shape ``(rows, columns)`` (or ``(rows,)``), else ParameterError."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name} must be an array of numbers ({exc})") from None
    shape = (rows,) if columns is None else (rows, columns)
    if arr.size == 0 and arr.ndim <= 1 and rows in (0, None):
        return arr.reshape((0,) + shape[1:])  # [] for "no nodes" or "no edges"
    want = "(n,)" if columns is None else f"(n, {columns})"
    if arr.ndim != len(shape) or (columns is not None and arr.shape[1] != columns):
        raise ParameterError(f"{name} must have shape {want}, got {arr.shape}")
    if rows is not None and arr.shape[0] != rows:
        raise ParameterError(f"{name} must have {rows} rows (one per edge), got {arr.shape[0]}")
    if np.isnan(arr).any():
        raise ParameterError(f"{name} contains NaN")
    return arr


def _finite(arr: np.ndarray, name: str) -> np.ndarray:
    if not np.isfinite(arr).all():
        raise ParameterError(f"{name} must be finite (no NaN or inf)")
    return arr


def _edge_array(edges: ArrayLike, n: int) -> np.ndarray:
    """``edges`` as int64 ``(m, 2)`` with endpoints in ``[0, n)`` and no self-loops."""
    arr = np.asarray(edges)
    if arr.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ParameterError(f"edges must have shape (m, 2), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        raise ParameterError(f"edges must be integer node indices, got dtype {arr.dtype}")
    arr = arr.astype(np.int64)
    bad = np.flatnonzero((arr < 0).any(axis=1) | (arr >= n).any(axis=1))
    if bad.size:
        k = int(bad[0])
        raise ParameterError(
            f"edge {k} = {tuple(arr[k].tolist())} refers to a node outside [0, {n}) "
            f"({bad.size} such edges)"
        )
    loops = np.flatnonzero(arr[:, 0] == arr[:, 1])
    if loops.size:
        k = int(loops[0])
        raise ParameterError(
            f"edge {k} = {tuple(arr[k].tolist())} is a self-loop ({loops.size} such edges); "
            "a term on one node belongs in the unary costs"
        )
    return arr


def _binary_labels(labels: ArrayLike, n: int) -> np.ndarray:
    arr = np.asarray(labels)
    if arr.shape != (n,):
        raise ParameterError(f"labels must have shape ({n},), got {arr.shape}")
    if arr.size and arr.dtype != bool:
        if not np.issubdtype(arr.dtype, np.integer) or not np.isin(arr, (0, 1)).all():
            raise ParameterError("binary labels must be bool or integers 0/1")
    return arr.astype(np.int64)


def _potts_labels(labels: ArrayLike, n: int, k: int) -> np.ndarray:
    arr = np.asarray(labels)
    if arr.shape != (n,):
        raise ParameterError(f"labels must have shape ({n},), got {arr.shape}")
    if n and (not np.issubdtype(arr.dtype, np.integer) or arr.min() < 0 or arr.max() >= k):
        raise ParameterError(f"labels must be integers in [0, {k})")
    return arr.astype(np.int64)


def _check_binary(
    unary: ArrayLike, edges: ArrayLike, pairwise: ArrayLike
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    u = _finite(_float_array(unary, "unary", 2, None), "unary")
    e = _edge_array(edges, u.shape[0])
    p = _finite(_float_array(pairwise, "pairwise", 4, e.shape[0]), "pairwise")
    return u, e, p


def _check_potts(
    unary: ArrayLike, edges: ArrayLike, weights: ArrayLike
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    try:
        shape = np.shape(unary)
    except ValueError:  # ragged nested lists
        shape = ()
    if len(shape) != 2 or shape[1] < 1:
        raise ParameterError(f"unary must have shape (n, K) with K >= 1, got {shape}")
    u = _float_array(unary, "unary", shape[1], None)
    if (u == -np.inf).any():
        raise ParameterError("unary contains -inf; use +inf to forbid a label")
    e = _edge_array(edges, u.shape[0])
    w = _finite(_float_array(weights, "weights", None, e.shape[0]), "weights")
    if (w < 0).any():
        k = int(np.flatnonzero(w < 0)[0])
        raise ParameterError(f"Potts weights must be >= 0, weights[{k}] = {w[k]}")
    return u, e, w


# ---------------------------------------------------------------------------------------
# binary energies: reduction to a cut


@dataclass(frozen=True)
class _Reduced:
    """A binary energy reparametrised as (constant +) per-node differences + edge capacities."""

    d: np.ndarray  # cost(label 1) - cost(label 0) per node, pairwise parts included
    pair: sparse.csr_array  # n x n float, entry (i, j) paid when x_i = 1 and x_j = 0
    slack: float  # total of the (tolerated, tiny) submodularity violations set to zero


def _reduce(d: np.ndarray, e: np.ndarray, a, b, c, dd) -> _Reduced:
    """Kolmogorov-Zabih reparametrisation of checked arrays; refuses non-submodular terms.

    ``d`` is each node's cost of label 1 minus its cost of label 0, ``a, b, c, dd`` the
    edges' ``E00, E01, E10, E11``. ``E(a, b) = A + (C - A) a + (D - C) b + (B + C - A - D)
    (1 - a) b`` with ``A..D = E00, E01, E10, E11``: two unary parts and one term paid when
    ``x_i = 0, x_j = 1``, i.e. by the capacity ``j -> i`` (j on the source side, i on the
    sink side).
    """
    n = d.shape[0]
    lam = b + c - a - dd
    negative = np.flatnonzero(lam < 0)  # the tolerance is only looked up where it can matter
    slack = 0.0
    if negative.size:
        size = np.abs(a) + np.abs(b) + np.abs(c) + np.abs(dd)
        bad = negative[lam[negative] < -_SUBMODULAR_RTOL * size[negative]]
        if bad.size:
            k = int(bad[0])
            raise ParameterError(
                f"pairwise term {k} on edge {tuple(e[k].tolist())} is not submodular: "
                f"E00 + E11 = {a[k] + dd[k]:.6g} > E01 + E10 = {b[k] + c[k]:.6g} "
                f"({bad.size} such terms); graph cuts minimise submodular energies only"
            )
        slack = float(np.sum(np.maximum(-lam, 0.0)))
        lam = np.maximum(lam, 0.0)
    d = d + np.bincount(e[:, 0], weights=c - a, minlength=n)
    d = d + np.bincount(e[:, 1], weights=dd - c, minlength=n)
    if not np.isfinite(d).all():
        raise ParameterError("unary and pairwise costs are too large: their sums overflow")
    # coo -> csr sums duplicate edges (and both terms of a pair given twice)
    pair = sparse.coo_array((lam, (e[:, 1], e[:, 0])), shape=(n, n)).tocsr()
    pair.eliminate_zeros()
    return _Reduced(d=d, pair=pair, slack=slack)


@dataclass(frozen=True)
class _Network:
    """The integer s-t network of a reduced energy, and what its rounding may cost."""

    capacity: sparse.csr_array  # (n + 2) x (n + 2) int32; source n, sink n + 1
    bound: float


def _quantise(r: _Reduced) -> _Network | None:
    """Scale and round the capacities to int32; None when no edge has capacity (decoupled).

    Terminal capacities first: node i wants the source (label 1) with strength ``-d_i`` or the
    sink with ``d_i``. A strength above the total capacity of the edges that could pull i to
    the other side decides i alone, so it is clipped to that total + 1 (in integer units):
    the minimum cut is unchanged, and huge unaries (hard constraints written as ``1e12``) no
    longer dictate the scale. The scale then maps the largest capacity, or sum of the two
    directions of an edge (a residual capacity can reach it), to ``2**30``. Only single
    capacities need to fit int32: SciPy holds the total flow in int64.
    """
    pair = r.pair
    if pair.nnz == 0:
        return None
    n = r.d.shape[0]
    src, snk = np.maximum(-r.d, 0.0), np.maximum(r.d, 0.0)
    out_f, in_f = pair.sum(axis=1), pair.sum(axis=0)
    terminal = np.maximum(np.minimum(src, out_f), np.minimum(snk, in_f))
    rows = np.repeat(np.arange(n), np.diff(pair.indptr))  # each entry's row, as in pair_q
    one_way = _one_way(rows, pair.indices)
    largest = max(_largest_both_ways(pair, one_way), float(terminal.max()))
    scale = min(_CAPACITY_LIMIT / largest, 1e290)

    q_pair = np.rint(pair.data * scale)
    err = np.abs(pair.data - q_pair / scale).sum()
    pair_q = sparse.csr_array((q_pair.astype(np.int64), pair.indices, pair.indptr), shape=(n, n))
    out_q, in_q = pair_q.sum(axis=1), pair_q.sum(axis=0)
    q_src, err_src = _terminal(src, out_q, scale)
    q_snk, err_snk = _terminal(snk, in_q, scale)

    widest = max(int(q_src.max()), int(q_snk.max()), int(_largest_both_ways(pair_q, one_way)))
    if widest > _INT32_MAX:  # only with ~2**30 edges at one node
        raise ParameterError(f"capacities do not fit int32 after scaling (largest {widest})")
    capacity = _network_csr(pair_q, rows, q_src, q_snk)
    return _Network(capacity=capacity, bound=2.0 * (err + err_src + err_snk) + r.slack)


def _network_csr(pair_q: sparse.csr_array, rows: np.ndarray, q_src: np.ndarray, q_snk):
    """The (n + 2) x (n + 2) int32 capacities in canonical CSR, assembled directly.

    Node i's row holds its positive edge capacities (``pair_q``'s row, columns ascending)
    and then its edge to the sink ``n + 1``; the source ``n``'s row its edges to the nodes;
    the sink's row is empty. The same matrix as building it from coordinates, without
    their sort. ``rows`` holds the row of each of ``pair_q``'s stored entries.
    """
    n = pair_q.shape[0]
    keep = pair_q.data > 0
    rows = rows[keep]
    to_sink = q_snk > 0
    per_row = np.bincount(rows, minlength=n) + to_sink
    from_source = np.flatnonzero(q_src > 0)
    if rows.size + int(to_sink.sum()) + from_source.size > _INT32_MAX:
        raise ParameterError("the network has more edges than SciPy's max-flow can index")
    indptr = np.zeros(n + 3, dtype=np.int32)  # int32 indices: what the max-flow works in
    np.cumsum(per_row, out=indptr[1 : n + 1])
    indptr[n + 1] = indptr[n] + from_source.size
    indptr[n + 2] = indptr[n + 1]
    indices = np.empty(int(indptr[-1]), dtype=np.int32)
    data = np.empty(int(indptr[-1]), dtype=np.int32)
    # entries of earlier rows' sink edges shift a row's edges to the right
    earlier = np.concatenate([[0], np.cumsum(to_sink)[:-1]])
    at = np.arange(rows.size) + earlier[rows]
    indices[at] = pair_q.indices[keep]
    data[at] = pair_q.data[keep]
    last = indptr[1 : n + 1][to_sink] - 1
    indices[last] = n + 1
    data[last] = q_snk[to_sink]
    indices[indptr[n] : indptr[n + 1]] = from_source
    data[indptr[n] : indptr[n + 1]] = q_src[from_source]
    return sparse.csr_array((data, indices, indptr), shape=(n + 2, n + 2))


def _one_way(rows: np.ndarray, columns: np.ndarray) -> bool:
    """True when no stored entry (``rows``, ``columns``) has its transpose: all strictly below
    the diagonal, or all above (every edge given as (lower, upper) node, as grids and
    expansion moves do)."""
    return bool(np.all(columns < rows) or np.all(columns > rows))


def _largest_both_ways(pair: sparse.csr_array, one_way: bool) -> float:
    """The largest entry of ``pair + pair.T``: with ``one_way`` the largest of ``pair``'s own
    (each entry meets only a zero), without the sparse sum and its transpose."""
    if one_way:
        return pair.data.max()
    return (pair + pair.T).tocsr().data.max()


def _terminal(strength: np.ndarray, opposing: np.ndarray, scale: float) -> tuple[np.ndarray, float]:
    """Rounded terminal capacities, clipped to ``opposing + 1``; and the rounding error of
    the unclipped ones (a clipped edge is never cut, and is rounded down, so it costs none)."""
    raw = np.rint(strength * scale)
    limit = opposing.astype(np.float64) + 1.0
    clipped = raw > limit
    q = np.where(clipped, limit, raw).astype(np.int64)
    err = np.abs(strength[~clipped] - raw[~clipped] / scale).sum()
    return q, float(err)


def _min_cut_source_side(capacity: sparse.csr_array, source: int, sink: int) -> np.ndarray:
    """Mask of the vertices reachable from ``source`` in the residual graph of a max flow."""
    flow = maximum_flow(capacity, source, sink, method=_FLOW_METHOD).flow
    residual = sparse.csr_array(capacity - flow)  # union pattern: both directions of each edge
    residual.data[residual.data < 0] = 0
    residual.eliminate_zeros()
    reached = breadth_first_order(residual, source, directed=True, return_predecessors=False)
    side = np.zeros(capacity.shape[0], dtype=bool)
    side[reached] = True
    return side


def minimize_binary(unary: ArrayLike, edges: ArrayLike, pairwise: ArrayLike) -> np.ndarray:
    """Exact minimum of a binary submodular energy by one s-t minimum cut.

    Parameters
    ----------
    unary : (n, 2) float
        Cost of label 0 and of label 1 for every node (finite, any sign). Huge costs used as
        hard constraints are fine: they are clipped without losing precision elsewhere.
    edges : (m, 2) int
        Node pairs ``(i, j)``, ``i != j``; repeated pairs add up.
    pairwise : (m, 4) float
        ``E00, E01, E10, E11`` per edge, ``E_ab`` the cost of ``x_i = a, x_j = b``. Each term
        must be submodular, ``E00 + E11 <= E01 + E10``, else ParameterError.

    Returns
    -------
    (n,) bool
        True where the label is 1. The labelling minimises the energy with the capacities
        rounded to integers (SciPy's max-flow needs int32); its energy exceeds the true
        minimum by at most :func:`binary_cut_bound`. Ties go to label 0. Without edges the
        result is the per-node argmin and exact.
    """
    u, e, p = _check_binary(unary, edges, pairwise)
    return _minimum_terms(u[:, 1] - u[:, 0], e, *p.T)


def _minimum_terms(d: np.ndarray, e: np.ndarray, a, b, c, dd) -> np.ndarray:
    """:func:`minimize_binary` from the label-1-minus-label-0 unary difference ``d`` and the
    edges' four terms, already valid (checked, or built valid, as a move's are)."""
    r = _reduce(d, e, a, b, c, dd)
    net = _quantise(r)
    if net is None:
        return r.d < 0
    n = d.shape[0]
    return _min_cut_source_side(net.capacity, n, n + 1)[:n]


def binary_cut_bound(unary: ArrayLike, edges: ArrayLike, pairwise: ArrayLike) -> float:
    """How much higher than the true minimum :func:`minimize_binary`'s energy can be.

    The cut is exact for the rounded capacities ``q_k / s``. For the cut's labelling ``x'``
    and a true minimiser ``x*``, ``E(x') - E(x*) <= sum_k |c_k - q_k / s| ([k cut by x'] +
    [k cut by x*]) <= 2 sum_k |c_k - q_k / s|``, which is returned (plus any submodularity
    violation within rounding that was set to zero). Each rounding error is at most
    ``0.5 / s`` and ``s = 2**30 / c_max``, so the bound is at most ``N c_max / 2**30`` for
    ``N`` capacities; it is 0 when nothing needed rounding. Float64 rounding in the sums of
    the costs themselves comes on top.
    """
    u, e, p = _check_binary(unary, edges, pairwise)
    r = _reduce(u[:, 1] - u[:, 0], e, *p.T)
    net = _quantise(r)
    return r.slack if net is None else float(net.bound)


def binary_energy(
    unary: ArrayLike, edges: ArrayLike, pairwise: ArrayLike, labels: ArrayLike
) -> float:
    """Energy ``sum_i U_i(x_i) + sum_k E_k(x_i, x_j)`` of a binary labelling (bool or 0/1)."""
    u = _finite(_float_array(unary, "unary", 2, None), "unary")
    e = _edge_array(edges, u.shape[0])
    p = _finite(_float_array(pairwise, "pairwise", 4, e.shape[0]), "pairwise")
    x = _binary_labels(labels, u.shape[0])
    total = u[np.arange(u.shape[0]), x].sum()
    total += p[np.arange(e.shape[0]), 2 * x[e[:, 0]] + x[e[:, 1]]].sum()
    return float(total)


# ---------------------------------------------------------------------------------------
# Potts: alpha-expansion


def _potts_energy(u: np.ndarray, e: np.ndarray, w: np.ndarray, f: np.ndarray) -> float:
    data = u[np.arange(u.shape[0]), f].sum()
    return float(data + w[f[e[:, 0]] != f[e[:, 1]]].sum())


def potts_energy(
    unary: ArrayLike, edges: ArrayLike, weights: ArrayLike, labels: ArrayLike
) -> float:
    """Energy ``sum_i U[i, f_i] + sum_k w_k [f_i != f_j]``; inf when a forbidden label is used."""
    u, e, w = _check_potts(unary, edges, weights)
    return _potts_energy(u, e, w, _potts_labels(labels, u.shape[0], u.shape[1]))


def _expansion_move(
    u: np.ndarray, e: np.ndarray, w: np.ndarray, f: np.ndarray, alpha: int
) -> np.ndarray | None:
    """The best labelling that changes some labels of ``f`` to ``alpha`` (None: no node can).

    Binary variable x_i = 1: node i switches to alpha. Nodes already at alpha, or for which
    alpha is forbidden (inf), keep their label and leave the cut: a term between such a node
    and a free one becomes a unary cost of the free one, so no inf enters the graph.
    """
    free = (f != alpha) & np.isfinite(u[:, alpha])
    if not free.any():
        return None
    where = np.flatnonzero(free)
    index = np.cumsum(free) - 1
    i, j = e[:, 0], e[:, 1]
    both_keep = w * (f[i] != f[j])  # E00
    j_moves = w * (f[i] != alpha)  # E01: i keeps f_i, j takes alpha
    i_moves = w * (f[j] != alpha)  # E10
    stay, move = u[where, f[where]], u[where, alpha]
    lone_i = free[i] & ~free[j]
    stay = stay + np.bincount(index[i[lone_i]], weights=both_keep[lone_i], minlength=where.size)
    move = move + np.bincount(index[i[lone_i]], weights=i_moves[lone_i], minlength=where.size)
    lone_j = free[j] & ~free[i]
    stay = stay + np.bincount(index[j[lone_j]], weights=both_keep[lone_j], minlength=where.size)
    move = move + np.bincount(index[j[lone_j]], weights=j_moves[lone_j], minlength=where.size)
    pair = free[i] & free[j]
    edges = np.stack([index[i[pair]], index[j[pair]]], axis=1)
    # valid by construction (finite costs: the labels kept and alpha are allowed; edges
    # between distinct free nodes), so the checks of the public entry are skipped
    terms = both_keep[pair], j_moves[pair], i_moves[pair], np.zeros(edges.shape[0])
    switch = _minimum_terms(move - stay, edges, *terms)
    g = f.copy()
    g[where[switch]] = alpha
    return g


def _exact_two_label(u: np.ndarray, e: np.ndarray, w: np.ndarray) -> np.ndarray:
    """K = 2: expanding label 1 from 'label 0 wherever allowed' is the whole binary problem."""
    f = np.where(np.isfinite(u[:, 0]), 0, 1)
    g = _expansion_move(u, e, w, f, 1)
    return f if g is None else g


def potts_expansion(
    unary: ArrayLike,
    edges: ArrayLike,
    weights: ArrayLike,
    *,
    labels: ArrayLike | None = None,
    max_cycles: int = 10,
) -> np.ndarray:
    """Approximate minimum of a Potts energy by alpha-expansion moves, each an exact cut.

    Parameters
    ----------
    unary : (n, K) float
        Cost of every label for every node; ``+inf`` forbids a label (each node needs one
        finite label).
    edges : (m, 2) int
        Node pairs, ``i != j``.
    weights : (m,) float
        Potts weights ``w >= 0``: the cost ``w_k`` is paid when the two labels differ.
    labels : (n,) int, optional
        Start labelling (must use allowed labels); default the per-node argmin of ``unary``.
    max_cycles : int, default 10
        At most this many cycles over the K labels.

    Returns
    -------
    (n,) int64
        Labels in ``0..K-1``. A move is accepted only when it lowers the energy; the loop stops
        after a cycle without one. The result admits no better expansion move (up to the
        rounding of :func:`binary_cut_bound`), and for non-negative costs its energy is at most
        twice the minimum. For K = 2 it is the exact minimum (up to that rounding).
    """
    u, e, w = _check_potts(unary, edges, weights)
    n, k = u.shape
    if not isinstance(max_cycles, (int, np.integer)) or max_cycles < 1:
        raise ParameterError(f"max_cycles must be a positive integer, got {max_cycles!r}")
    finite = np.isfinite(u)
    if n and not finite.any(axis=1).all():
        node = int(np.flatnonzero(~finite.any(axis=1))[0])
        raise ParameterError(f"node {node} has every label forbidden (all unary costs inf)")
    if labels is None:
        f = np.argmin(u, axis=1).astype(np.int64)
    else:
        f = _potts_labels(labels, n, k)
        bad = np.flatnonzero(~finite[np.arange(n), f])
        if bad.size:
            raise ParameterError(f"start labels use a forbidden label at node {int(bad[0])}")
    if n == 0 or k == 1:
        return f
    energy = _potts_energy(u, e, w, f)
    if k == 2:
        f, energy = _better(u, e, w, f, energy, _exact_two_label(u, e, w))
    tol = _ACCEPT_RTOL * (np.abs(u[np.arange(n), f]).sum() + w.sum())
    # Cycles over the labels until a whole cycle brings nothing. A move depends only on the
    # labelling it starts from, so once the last k moves failed every other one would too:
    # stopping there skips the end of the last cycle and gives the same labels.
    failures = 0
    for move in range(max_cycles * k):
        g = _expansion_move(u, e, w, f, move % k)
        g_energy = None if g is None else _potts_energy(u, e, w, g)
        if g_energy is not None and g_energy < energy - tol:
            f, energy, failures = g, g_energy, 0
        else:
            failures += 1
            if failures == k:
                break
    return f


def _better(
    u: np.ndarray, e: np.ndarray, w: np.ndarray, f: np.ndarray, energy: float, g: np.ndarray
) -> tuple[np.ndarray, float]:
    g_energy = _potts_energy(u, e, w, g)
    return (g, g_energy) if g_energy < energy else (f, energy)


# ---------------------------------------------------------------------------------------
# grids


def grid_edges(
    mask: ArrayLike, spacing: ArrayLike = (1.0, 1.0, 1.0)
) -> tuple[np.ndarray, np.ndarray]:
    """6-connected neighbour pairs between the True voxels of a 3D mask.

    Parameters
    ----------
    mask : (X, Y, Z) bool
        Voxels that are nodes; node ``q`` is the voxel ``np.flatnonzero(mask)[q]``.
    spacing : 3 floats, default (1, 1, 1)
        Voxel size along each axis.

    Returns
    -------
    edges : (m, 2) int64
        ``(lower, upper)`` node pairs, the pairs along axis 0 first, then 1, then 2.
    lengths : (m,) float
        The spacing along the pair's axis (to weight a boundary term by area or length).
    """
    m = np.asarray(mask)
    if m.ndim != 3 or m.dtype != bool:
        raise ParameterError(f"mask must be a 3D bool array, got {m.ndim}D of dtype {m.dtype}")
    step = _float_array(spacing, "spacing", None, None)
    if step.shape != (3,) or not np.isfinite(step).all() or (step <= 0).any():
        raise ParameterError(f"spacing must be 3 positive finite numbers, got {spacing!r}")
    node = np.full(m.shape, -1, dtype=np.int64)
    node[m] = np.arange(int(m.sum()))
    pairs, lengths = [], []
    for axis in range(3):
        lo = node[tuple(slice(0, -1) if a == axis else slice(None) for a in range(3))]
        hi = node[tuple(slice(1, None) if a == axis else slice(None) for a in range(3))]
        both = (lo >= 0) & (hi >= 0)
        pairs.append(np.stack([lo[both], hi[both]], axis=1))
        lengths.append(np.full(int(both.sum()), step[axis]))
    return np.concatenate(pairs), np.concatenate(lengths)
