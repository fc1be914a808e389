"""Tests of medseg.mrf._cut: exact binary cuts and Potts alpha-expansion against brute force."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from medseg.errors import ParameterError
from medseg.mrf._cut import (
    binary_cut_bound,
    binary_energy,
    grid_edges,
    minimize_binary,
    potts_energy,
    potts_expansion,
)


def all_binary(n):
    """Every labelling of n binary nodes, (2**n, n) int."""
    return (np.arange(2**n)[:, None] >> np.arange(n)) & 1


def all_labellings(n, k):
    return np.array(list(itertools.product(range(k), repeat=n)), dtype=np.int64)


def binary_energies(unary, edges, pairwise, xs):
    """Energies of many labellings at once (the reference for binary_energy)."""
    n = unary.shape[0]
    e = unary[np.arange(n), xs].sum(axis=1)
    if len(edges):
        e = e + pairwise[np.arange(len(edges)), 2 * xs[:, edges[:, 0]] + xs[:, edges[:, 1]]].sum(1)
    return e


def potts_energies(unary, edges, weights, fs):
    n = unary.shape[0]
    with np.errstate(invalid="ignore"):
        e = unary[np.arange(n), fs].sum(axis=1)
    return e + ((fs[:, edges[:, 0]] != fs[:, edges[:, 1]]) * weights).sum(axis=1)


def random_submodular(rng, m, scale=1.0):
    """Random E00..E11 of both signs with E00 + E11 <= E01 + E10 (mostly strictly)."""
    p = rng.normal(scale=scale, size=(m, 4))
    lam = p[:, 1] + p[:, 2] - p[:, 0] - p[:, 3]
    p[:, 1] += np.maximum(-lam, 0.0) + rng.uniform(0, scale, m) * (rng.random(m) < 0.8)
    return p


def tiny_grid_problem(rng, shape=(2, 2, 3), extra=6):
    """A 6-connected grid plus a few random (duplicate and reversed) edges."""
    edges, _ = grid_edges(np.ones(shape, dtype=bool))
    n = int(np.prod(shape))
    more = rng.integers(0, n, size=(extra, 2))
    more = more[more[:, 0] != more[:, 1]]
    edges = np.concatenate([edges, more, edges[:3], edges[3:5, ::-1]])
    unary = rng.normal(scale=2.0, size=(n, 2))
    return unary, edges, random_submodular(rng, len(edges))


# ---------------------------------------------------------------------------------------
# minimize_binary


@pytest.mark.parametrize("seed", range(8))
def test_binary_cut_is_the_brute_force_minimum(seed):
    rng = np.random.default_rng(seed)
    unary, edges, pairwise = tiny_grid_problem(rng)
    x = minimize_binary(unary, edges, pairwise)
    assert x.dtype == bool and x.shape == (unary.shape[0],)
    best = binary_energies(unary, edges, pairwise, all_binary(unary.shape[0])).min()
    got = binary_energy(unary, edges, pairwise, x)
    bound = binary_cut_bound(unary, edges, pairwise)
    magnitude = np.abs(unary).sum() + np.abs(pairwise).sum()
    assert bound <= 1e-6 * magnitude  # the quantisation bound is tight ...
    assert best - 1e-12 * magnitude <= got <= best + bound + 1e-12 * magnitude  # ... and holds


def test_binary_energy_matches_reference():
    rng = np.random.default_rng(3)
    unary, edges, pairwise = tiny_grid_problem(rng)
    xs = all_binary(unary.shape[0])[::97]
    ref = binary_energies(unary, edges, pairwise, xs)
    assert [binary_energy(unary, edges, pairwise, x) for x in xs] == pytest.approx(ref)
    assert binary_energy(unary, edges, pairwise, xs[5].astype(bool)) == pytest.approx(ref[5])


def test_duplicate_edges_add_up():
    # node 1 prefers label 1 by 1.0; a Potts edge to the surely-0 node 0 pulls it when w > 1
    unary = np.array([[0.0, 5.0], [1.0, 0.0]])
    quarter = [[0.0, 0.75, 0.75, 0.0]]
    assert minimize_binary(unary, [[0, 1]], quarter).tolist() == [False, True]
    # the same term twice (once reversed, E01 and E10 swap) adds up to 1.5: pulled
    assert minimize_binary(unary, [[0, 1], [1, 0]], quarter * 2).tolist() == [False, False]
    assert minimize_binary(unary, [[0, 1], [0, 1]], quarter * 2).tolist() == [False, False]


def test_label_convention():
    # no edges: the per-node argmin, ties to 0
    x = minimize_binary([[0.0, 10.0], [10.0, 0.0], [1.0, 1.0]], np.zeros((0, 2), int), [])
    assert x.tolist() == [False, True, False]
    # through the graph (weak edges), including a node with no capacity at all
    unary = [[0.0, 10.0], [10.0, 0.0], [0.0, 0.0], [5.0, 5.0]]
    x = minimize_binary(unary, [[0, 1], [2, 3]], [[0.0, 0.1, 0.1, 0.0], [0.0, 0.0, 0.0, 0.0]])
    assert x.tolist() == [False, True, False, False]
    # a strong Potts edge pulls a weak node to its neighbour's label, in both directions
    potts = [[0.0, 100.0, 100.0, 0.0]]
    assert minimize_binary([[0.0, 10.0], [1.0, 0.0]], [[0, 1]], potts).tolist() == [False] * 2
    assert minimize_binary([[10.0, 0.0], [0.0, 1.0]], [[0, 1]], potts).tolist() == [True] * 2
    assert minimize_binary([[0.0, 1.0], [10.0, 0.0]], [[0, 1]], potts).tolist() == [True] * 2


def test_asymmetric_terms_orientation():
    """E01 and E10 are not interchangeable: the term is read as E[x_i, x_j]."""
    unary = np.zeros((2, 2))
    # only (x_0, x_1) = (1, 0) is cheap: E10 = -5
    pairwise = [[0.0, 6.0, -5.0, 0.0]]
    assert minimize_binary(unary, [[0, 1]], pairwise).tolist() == [True, False]
    assert minimize_binary(unary, [[1, 0]], pairwise).tolist() == [False, True]


def test_large_magnitude_ranges_keep_precision():
    """Unaries of ~1e4 (some decisive, some nearly tied) beside edge terms of ~1e-3."""
    for seed in range(4):
        rng = np.random.default_rng(100 + seed)
        unary, edges, _ = tiny_grid_problem(rng)
        n = unary.shape[0]
        unary = 1e4 + rng.normal(scale=1e-3, size=(n, 2))
        decisive = rng.random(n) < 0.3
        unary[decisive, rng.integers(0, 2, int(decisive.sum()))] += 1e4
        pairwise = random_submodular(rng, len(edges), scale=1e-3)
        x = minimize_binary(unary, edges, pairwise)
        best = binary_energies(unary, edges, pairwise, all_binary(n)).min()
        bound = binary_cut_bound(unary, edges, pairwise)
        assert bound < 1e-9  # the 1e4 unaries do not set the scale
        assert binary_energy(unary, edges, pairwise, x) <= best + bound + 1e-10


def test_huge_hard_constraint_costs():
    unary = np.array([[0.0, 1e12], [0.0, 0.0], [0.0, 0.0], [1e12, 0.0]])
    edges = [[0, 1], [1, 2], [2, 3]]
    pairwise = [[0.0, 1.0, 1.0, 0.0], [0.0, 1.0, 1.0, 0.0], [0.0, 1.5, 1.5, 0.0]]
    assert minimize_binary(unary, edges, pairwise).tolist() == [False, False, True, True]
    assert binary_cut_bound(unary, edges, pairwise) < 1e-6


def test_empty_problems():
    assert minimize_binary(np.zeros((0, 2)), np.zeros((0, 2), int), np.zeros((0, 4))).shape == (0,)
    assert minimize_binary([[2.0, 1.0]], [], []).tolist() == [True]
    assert binary_cut_bound([[2.0, 1.0]], [], []) == 0.0
    assert binary_energy(np.zeros((0, 2)), [], [], []) == 0.0
    assert potts_energy(np.zeros((0, 2)), [], [], []) == 0.0
    assert potts_expansion(np.zeros((0, 3)), [], []).shape == (0,)
    assert potts_expansion([[3.0, 1.0, 2.0], [0.0, 0.0, 5.0]], [], []).tolist() == [1, 0]


@pytest.mark.parametrize(
    "unary, edges, pairwise, match",
    [
        ([[0, 0], [0, 0]], [[0, 1]], [[0.0, 0.0, 0.0, 1.0]], "not submodular"),
        ([[0, 0], [0, 0]], [[0, 1]], [[0.0, -1.0, -1.0, 0.0]], "not submodular"),
        ([[0, np.nan], [0, 0]], [[0, 1]], [[0, 1, 1, 0]], "NaN"),
        ([[0, np.inf], [0, 0]], [[0, 1]], [[0, 1, 1, 0]], "finite"),
        ([[0, 0], [0, 0]], [[0, 1]], [[0, np.nan, 1, 0]], "NaN"),
        ([[0, 0], [0, 0]], [[0, 2]], [[0, 1, 1, 0]], "outside"),
        ([[0, 0], [0, 0]], [[-1, 1]], [[0, 1, 1, 0]], "outside"),
        ([[0, 0], [0, 0]], [[1, 1]], [[0, 1, 1, 0]], "self-loop"),
        ([[0, 0], [0, 0]], [[0.0, 1.0]], [[0, 1, 1, 0]], "integer"),
        ([[0, 0], [0, 0]], [[0, 1]], [[0, 1, 1]], "shape"),
        ([[0, 0], [0, 0]], [[0, 1]], [[0, 1, 1, 0]] * 2, "rows"),
        ([[0, 0, 0]], [], [], "shape"),
    ],
)
def test_binary_refuses_bad_input(unary, edges, pairwise, match):
    with pytest.raises(ParameterError, match=match):
        minimize_binary(unary, edges, pairwise)


def test_submodularity_tolerance_is_relative():
    # violated by 1 part in 1e14 of the magnitudes: rounding, accepted (and counted in the bound)
    big = 1e6
    term = [[big, big, big, big * (1 + 1e-14)]]
    x = minimize_binary([[0.0, 1.0], [0.0, 1.0]], [[0, 1]], term)
    assert x.tolist() == [False, False]
    with pytest.raises(ParameterError, match="not submodular"):
        minimize_binary([[0.0, 1.0], [0.0, 1.0]], [[0, 1]], [[big, big, big, big * (1 + 1e-9)]])


# ---------------------------------------------------------------------------------------
# potts_expansion


def expansion_moves_do_not_improve(unary, edges, weights, f, tol):
    """Brute force over every expansion move from f: none lowers the energy beyond tol."""
    n, k = unary.shape
    e0 = potts_energy(unary, edges, weights, f)
    subsets = all_binary(n).astype(bool)
    for alpha in range(k):
        moved = np.where(subsets, alpha, f[None, :])
        assert potts_energies(unary, edges, weights, moved).min() >= e0 - tol


def potts_binary_terms(weights):
    w = np.asarray(weights, dtype=float)
    return np.stack([0 * w, w, w, 0 * w], axis=1)


@pytest.mark.parametrize("seed", range(4))
def test_potts_two_labels_is_exact(seed):
    rng = np.random.default_rng(seed)
    edges, _ = grid_edges(np.ones((2, 2, 3), dtype=bool))
    unary = rng.uniform(0, 3, size=(12, 2))
    weights = rng.uniform(0, 2, size=len(edges))
    best = potts_energies(unary, edges, weights, all_binary(12)).min()
    bound = binary_cut_bound(unary, edges, potts_binary_terms(weights))
    cut = minimize_binary(unary, edges, potts_binary_terms(weights))
    for start in (None, np.ones(12, int), rng.integers(0, 2, 12)):
        f = potts_expansion(unary, edges, weights, labels=start)
        assert f.dtype == np.int64 and set(f.tolist()) <= {0, 1}
        got = potts_energy(unary, edges, weights, f)
        assert got <= best + bound + 1e-12
        assert got == pytest.approx(potts_energy(unary, edges, weights, cut.astype(int)), abs=bound)


@pytest.mark.parametrize("k", [3, 4])
@pytest.mark.parametrize("seed", range(5))
def test_potts_expansion_bound_and_local_optimality(k, seed):
    rng = np.random.default_rng(10 * k + seed)
    edges, _ = grid_edges(np.ones((2, 2, 2), dtype=bool))
    unary = rng.uniform(0, 3, size=(8, k))
    weights = rng.uniform(0, 2, size=len(edges))
    f = potts_expansion(unary, edges, weights)
    got = potts_energy(unary, edges, weights, f)
    best = potts_energies(unary, edges, weights, all_labellings(8, k)).min()
    assert best - 1e-12 <= got <= 2 * best + 1e-9
    expansion_moves_do_not_improve(unary, edges, weights, f, tol=1e-6)


def test_potts_expansion_stops_after_k_failed_moves_with_the_labels_of_whole_cycles(
    monkeypatch,
):
    """The early stop skips only moves that would fail: same labels as cycling until a
    whole cycle brings nothing (the loop written out here), in fewer moves."""
    from medseg.mrf import _cut

    move = _cut._expansion_move

    def whole_cycles(u, e, w):
        f = np.argmin(u, axis=1)
        energy = _cut._potts_energy(u, e, w, f)
        tol = _cut._ACCEPT_RTOL * (np.abs(u[np.arange(len(u)), f]).sum() + w.sum())
        moves = 0
        while True:
            improved = False
            for alpha in range(u.shape[1]):
                g = move(u, e, w, f, alpha)
                moves += 1
                if g is not None and _cut._potts_energy(u, e, w, g) < energy - tol:
                    f, energy, improved = g, _cut._potts_energy(u, e, w, g), True
            if not improved:
                return f, moves

    calls = []
    monkeypatch.setattr(_cut, "_expansion_move", lambda *a: calls.append(1) or move(*a))
    saved = 0
    for seed in range(8):
        rng = np.random.default_rng(700 + seed)
        edges, _ = grid_edges(np.ones((3, 3, 4), dtype=bool))
        unary = rng.uniform(0, 3, size=(36, 3))
        weights = rng.uniform(0, 2, size=len(edges))
        calls.clear()
        f = potts_expansion(unary, edges, weights)
        expected, moves = whole_cycles(unary, edges, weights)
        np.testing.assert_array_equal(f, expected)
        assert len(calls) <= moves
        saved += moves - len(calls)
    assert saved > 0


def test_potts_expansion_usually_optimal():
    hits = 0
    for seed in range(10):
        rng = np.random.default_rng(500 + seed)
        edges, _ = grid_edges(np.ones((2, 2, 2), dtype=bool))
        unary = rng.uniform(0, 3, size=(8, 3))
        weights = rng.uniform(0, 2, size=len(edges))
        f = potts_expansion(unary, edges, weights)
        best = potts_energies(unary, edges, weights, all_labellings(8, 3)).min()
        hits += potts_energy(unary, edges, weights, f) <= best + 1e-9
    assert hits >= 7


def test_potts_expansion_reaches_the_optimum_on_an_easy_case():
    """Nodes 0-3 are surely label 0; nodes 4-7 weakly prefer 1 but strong edges make them 0."""
    edges, _ = grid_edges(np.ones((2, 2, 2), dtype=bool))  # axis 0 splits nodes 0-3 / 4-7
    unary = np.full((8, 3), 50.0)
    unary[:4, 0] = 0.0
    unary[4:] = [0.5, 0.0, 0.5]
    weights = np.full(len(edges), 10.0)
    start = np.argmin(unary, axis=1)
    assert start.tolist() == [0] * 4 + [1] * 4  # the argmin start is not optimal ...
    f = potts_expansion(unary, edges, weights)
    assert f.tolist() == [0] * 8  # ... expansion moves all of 4-7 at once
    best = potts_energies(unary, edges, weights, all_labellings(8, 3)).min()
    assert potts_energy(unary, edges, weights, f) == best == 2.0


@pytest.mark.parametrize("seed", range(4))
def test_potts_infinite_unaries_are_respected(seed):
    rng = np.random.default_rng(200 + seed)
    edges, _ = grid_edges(np.ones((2, 2, 2), dtype=bool))
    unary = rng.uniform(0, 3, size=(8, 3))
    forbid = rng.random((8, 3)) < 0.35
    forbid[np.arange(8), rng.integers(0, 3, 8)] = False  # one allowed label per node
    unary[forbid] = np.inf
    weights = rng.uniform(0, 4, size=len(edges))
    f = potts_expansion(unary, edges, weights)
    assert not forbid[np.arange(8), f].any()
    got = potts_energy(unary, edges, weights, f)
    best = potts_energies(unary, edges, weights, all_labellings(8, 3)).min()
    assert np.isfinite(got) and got <= 2 * best + 1e-9
    expansion_moves_do_not_improve(unary, edges, weights, f, tol=1e-6)


def test_potts_forbidden_label_resists_strong_neighbours():
    # node 1 would follow its neighbours to label 0 (it pays 20 on its edges), but 0 is forbidden
    edges = [[0, 1], [1, 2], [0, 2]]
    unary = np.array([[0.0, 50.0, 50.0], [np.inf, 5.0, 6.0], [0.0, 50.0, 50.0]])
    f = potts_expansion(unary, edges, [10.0, 10.0, 10.0])
    assert f.tolist() == [0, 1, 0]
    assert potts_energy(unary, edges, [10.0] * 3, f) == 25.0
    # K = 2 with forbidden labels: exact over the allowed labellings
    unary = np.array([[0.0, 9.0], [np.inf, 5.0], [0.0, 1.0], [3.0, np.inf]])
    edges = np.array([[0, 1], [1, 2], [2, 3], [0, 3]])
    weights = np.array([4.0, 6.0, 2.0, 1.0])
    f = potts_expansion(unary, edges, weights)
    best = potts_energies(unary, edges, weights, all_binary(4)).min()
    assert potts_energy(unary, edges, weights, f) == pytest.approx(best)


@pytest.mark.parametrize(
    "unary, edges, weights, kwargs, match",
    [
        ([[0, 1], [1, 0]], [[0, 1]], [-1.0], {}, ">= 0"),
        ([[0, 1], [1, 0]], [[0, 1]], [np.nan], {}, "NaN"),
        ([[0, 1], [1, 0]], [[0, 1]], [np.inf], {}, "finite"),
        ([[np.inf, np.inf], [1, 0]], [[0, 1]], [1.0], {}, "every label forbidden"),
        ([[0, -np.inf], [1, 0]], [[0, 1]], [1.0], {}, "-inf"),
        ([[0, np.nan], [1, 0]], [[0, 1]], [1.0], {}, "NaN"),
        ([[0, 1], [1, 0]], [[0, 0]], [1.0], {}, "self-loop"),
        ([[0, 1], [1, 0]], [[0, 5]], [1.0], {}, "outside"),
        ([[0, 1], [1, 0]], [[0, 1]], [1.0, 2.0], {}, "rows"),
        ([[0, np.inf], [1, 0]], [[0, 1]], [1.0], {"labels": [1, 0]}, "forbidden label"),
        ([[0, 1], [1, 0]], [[0, 1]], [1.0], {"labels": [0, 2]}, r"\[0, 2\)"),
        ([[0, 1], [1, 0]], [[0, 1]], [1.0], {"max_cycles": 0}, "max_cycles"),
        ([0.0, 1.0], [], [], {}, "shape"),
        ([[0.0, 1.0], [1.0]], [], [], {}, "shape"),
    ],
)
def test_potts_refuses_bad_input(unary, edges, weights, kwargs, match):
    with pytest.raises(ParameterError, match=match):
        potts_expansion(unary, edges, weights, **kwargs)


def test_potts_energy_values():
    unary = np.array([[0.0, 1.0, np.inf], [2.0, 0.0, 1.0]])
    assert potts_energy(unary, [[0, 1]], [3.0], [0, 1]) == 3.0
    assert potts_energy(unary, [[0, 1]], [3.0], [1, 1]) == 1.0
    assert potts_energy(unary, [[0, 1]], [3.0], [2, 2]) == np.inf


# ---------------------------------------------------------------------------------------
# grid_edges


def test_grid_edges_full_block_counts_and_lengths():
    edges, lengths = grid_edges(np.ones((3, 4, 5), dtype=bool), spacing=(0.5, 2.0, 3.0))
    assert edges.dtype == np.int64 and edges.shape == (2 * 4 * 5 + 3 * 3 * 5 + 3 * 4 * 4, 2)
    coords = np.stack(np.unravel_index(edges, (3, 4, 5)), axis=-1)  # (m, 2, 3)
    step = coords[:, 1] - coords[:, 0]
    assert (np.abs(step).sum(axis=1) == 1).all() and (step >= 0).all()
    axis = np.argmax(step, axis=1)
    assert lengths.tolist() == np.array([0.5, 2.0, 3.0])[axis].tolist()
    assert np.bincount(axis).tolist() == [2 * 4 * 5, 3 * 3 * 5, 3 * 4 * 4]


def test_grid_edges_numbering_follows_flatnonzero():
    rng = np.random.default_rng(7)
    mask = rng.random((4, 3, 5)) < 0.6
    edges, lengths = grid_edges(mask)
    voxels = np.flatnonzero(mask)
    coords = np.stack(np.unravel_index(voxels, mask.shape), axis=1)
    expected = {
        (a, b)
        for a in range(len(voxels))
        for b in range(len(voxels))
        if np.abs(coords[b] - coords[a]).sum() == 1 and voxels[b] > voxels[a]
    }
    assert {tuple(p) for p in edges.tolist()} == expected and len(edges) == len(expected)
    assert (lengths == 1.0).all()


@pytest.mark.parametrize(
    "mask, spacing",
    [
        (np.ones((3, 3), dtype=bool), (1, 1, 1)),
        (np.ones((3, 3, 3), dtype=np.uint8), (1, 1, 1)),
        (np.ones((3, 3, 3), dtype=bool), (1, 1)),
        (np.ones((3, 3, 3), dtype=bool), (1, 0, 1)),
        (np.ones((3, 3, 3), dtype=bool), (1, np.nan, 1)),
    ],
)
def test_grid_edges_refuses_bad_input(mask, spacing):
    with pytest.raises(ParameterError):
        grid_edges(mask, spacing)


def test_grid_cut_separates_two_regions():
    """End to end on a grid: a noisy two-region volume is recovered exactly by the cut."""
    rng = np.random.default_rng(11)
    truth = np.zeros((6, 6, 6), dtype=bool)
    truth[:, :, 3:] = True
    mask = np.ones_like(truth)
    edges, lengths = grid_edges(mask)
    signal = truth.ravel() + rng.normal(scale=0.6, size=truth.size)
    unary = np.stack([(signal - 0.0) ** 2, (signal - 1.0) ** 2], axis=1)
    x = minimize_binary(unary, edges, potts_binary_terms(2.0 * lengths))
    assert (x == truth.ravel()).mean() > 0.98
    assert binary_energy(unary, edges, potts_binary_terms(2.0 * lengths), x) <= binary_energy(
        unary, edges, potts_binary_terms(2.0 * lengths), truth.ravel()
    ) + binary_cut_bound(unary, edges, potts_binary_terms(2.0 * lengths))


# ---------------------------------------------------------------------------------------
# the s-t network


def coordinates_network(pair_q, q_src, q_snk):
    """The capacities built from coordinates and summed by SciPy (the reference)."""
    from scipy import sparse

    n = pair_q.shape[0]
    coo = pair_q.tocoo()
    nodes = np.arange(n)
    rows = np.concatenate([coo.row, np.full(n, n), nodes])
    cols = np.concatenate([coo.col, nodes, np.full(n, n + 1)])
    data = np.concatenate([coo.data, q_src, q_snk])
    keep = data > 0
    shape = (n + 2, n + 2)
    return sparse.coo_array((data[keep], (rows[keep], cols[keep])), shape=shape).tocsr()


@pytest.mark.parametrize("seed", range(6))
def test_network_is_the_coordinates_one(seed):
    # integer edge capacities with zeros among them (rounded to nothing), nodes without a
    # terminal edge, the source and sink rows: the direct assembly against SciPy's
    from scipy import sparse

    from medseg.mrf._cut import _network_csr

    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 40))
    dense = rng.integers(0, 4, size=(n, n)) * (rng.random((n, n)) < 0.3)
    np.fill_diagonal(dense, 0)
    pair_q = sparse.csr_array(dense.astype(np.int64))
    pair_q.data[::3] = 0  # stored zeros, as rounding leaves them
    q_src = rng.integers(0, 5, n) * (rng.random(n) < 0.6)
    q_snk = rng.integers(0, 5, n) * (rng.random(n) < 0.6)
    rows = np.repeat(np.arange(n), np.diff(pair_q.indptr))
    capacity = _network_csr(pair_q, rows, q_src, q_snk)
    reference = coordinates_network(pair_q, q_src, q_snk)
    assert capacity.dtype == np.int32 and capacity.shape == reference.shape
    for attribute in ("indptr", "indices", "data"):
        np.testing.assert_array_equal(getattr(capacity, attribute), getattr(reference, attribute))


@pytest.mark.parametrize("seed", range(4))
def test_largest_two_way_capacity(seed):
    # edges given once, lower -> upper (a grid's), take the short cut; with duplicate and
    # reversed edges the pair's two directions add up: both as SciPy's sum with its transpose
    from medseg.mrf import _cut

    rng = np.random.default_rng(seed)
    for extra, one_way in ((0, True), (8, False)):
        unary, edges, pairwise = tiny_grid_problem(rng, shape=(3, 3, 4), extra=extra)
        if one_way:
            edges, pairwise = edges[:-5], pairwise[:-5]  # no repeated or reversed edges
        else:  # grid edges 3 and 4 and their reversed copies: the two-way sum is largest
            pairwise[[3, 4, -2, -1]] = [0.0, 10.0, 10.0, 0.0]
        reduced = _cut._reduce(unary[:, 1] - unary[:, 0], edges, *pairwise.T)
        pair = reduced.pair
        rows = np.repeat(np.arange(pair.shape[0]), np.diff(pair.indptr))
        assert _cut._one_way(rows, pair.indices) == one_way
        expected = (reduced.pair + reduced.pair.T).tocsr().data.max()
        assert _cut._largest_both_ways(reduced.pair, one_way) == expected
