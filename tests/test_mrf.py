"""Tests of medseg.mrf: model validation, exactness against exhaustive search and HiGHS."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from medseg.errors import ProblemDefinitionError, ResourceLimitError
from medseg.mrf import (
    MRF,
    exhaustive_search,
    factor_tree_cover,
    icm,
    is_factor_forest,
    solve,
    solve_ilp,
)
from medseg.mrf._decode import sequential_decode
from medseg.mrf._kernels import beliefs, forbidden_cost, working_tables

# float32 tables: sums of a few dozen entries of size ~1 carry rounding of this order
EPS = 1e-4


def random_mixed_problem(rng, n, max_labels, n_pairs, n_triplets, forbid=0.0):
    """Random MRF with per-variable label counts and factors of order 1, 2 and 3."""
    labels = rng.integers(2, max_labels + 1, size=n)
    unaries = [rng.normal(size=int(m)) for m in labels]
    factors = []
    for v in rng.choice(n, size=min(n, 2), replace=False):
        factors.append(([int(v)], rng.normal(size=int(labels[v]))))
    for scope_size, count in ((2, n_pairs), (3, n_triplets)):
        scopes = list(itertools.combinations(range(n), scope_size))
        for j in rng.choice(len(scopes), size=min(count, len(scopes)), replace=False):
            scope = list(rng.permutation(scopes[j]))
            table = rng.normal(size=tuple(int(labels[v]) for v in scope))
            if forbid:
                table[rng.random(table.shape) < forbid] = np.inf
            factors.append((scope, table))
    return MRF(unaries, factors)


def brute_energy(unaries, factors, x):
    e = sum(unaries[i][x[i]] for i in range(len(x)))
    for scope, table in factors:
        e += table[tuple(x[v] for v in scope)]
    return e


# ----------------------------------------------------------------------------- model
def test_energy_matches_a_direct_sum_over_factors():
    rng = np.random.default_rng(0)
    unaries = [rng.normal(size=m) for m in (2, 3, 4, 3)]
    factors = [
        ((0, 2), rng.normal(size=(2, 4))),
        ((3, 1, 0), rng.normal(size=(3, 3, 2))),
        ((1,), rng.normal(size=3)),
    ]
    mrf = MRF(unaries, factors)
    for x in itertools.product(range(2), range(3), range(4), range(3)):
        expected = brute_energy(unaries, factors, x)
        assert mrf.energy(np.array(x)) == pytest.approx(expected, rel=1e-6, abs=1e-6)


def test_from_triplets_keeps_float32_tables_without_copy():
    rng = np.random.default_rng(1)
    tables = rng.random((3, 4, 4, 4), dtype=np.float32)
    mrf = MRF.from_triplets(rng.random((5, 4)), [[0, 1, 2], [1, 2, 3], [2, 3, 4]], tables)
    assert np.shares_memory(mrf.groups[3].tables, tables)
    x = np.array([1, 0, 3, 2, 1])
    expected = mrf.unaries[np.arange(5), x].sum() + tables[0, 1, 0, 3] + tables[1, 0, 3, 2]
    expected += tables[2, 3, 2, 1]
    assert mrf.energy(x) == pytest.approx(float(expected), rel=1e-6)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"tables": np.zeros((2, 3, 3, 2))}, r"must be \(2, 3, 3, 3\)"),
        ({"cliques": [[0, 1, 9], [1, 2, 3]]}, "outside 0..4"),
        ({"cliques": [[0, 1, 1], [1, 2, 3]]}, "repeated variable"),
        ({"cliques": [[0, 1, 2], [2, 0, 1]]}, "duplicated factors"),
        ({"cliques": [[0.0, 1.0, 2.0], [1.0, 2.0, 3.0]]}, "integer array"),
        ({"pairs": [[0, 1]]}, "given together"),
    ],
)
def test_from_triplets_rejects_malformed_problems(kwargs, match):
    args = {
        "unaries": np.zeros((5, 3)),
        "cliques": [[0, 1, 2], [1, 2, 3]],
        "tables": np.zeros((2, 3, 3, 3)),
    }
    args.update(kwargs)
    with pytest.raises(ProblemDefinitionError, match=match):
        MRF.from_triplets(args.pop("unaries"), args.pop("cliques"), args.pop("tables"), **args)


@pytest.mark.parametrize("bad", [np.nan, -np.inf])
def test_nan_and_negative_infinite_costs_are_refused(bad):
    tables = np.zeros((1, 2, 2, 2))
    tables[0, 1, 0, 1] = bad
    with pytest.raises(ProblemDefinitionError, match=r"index \(0, 1, 0, 1\)"):
        MRF.from_triplets(np.zeros((3, 2)), [[0, 1, 2]], tables)
    unaries = np.zeros((3, 2))
    unaries[2, 1] = bad
    with pytest.raises(ProblemDefinitionError, match="unaries"):
        MRF(unaries)


def test_general_form_rejects_bad_factors():
    unaries = [np.zeros(2), np.zeros(3), np.zeros(2)]
    with pytest.raises(ProblemDefinitionError, match=r"must be \(2, 3\)"):
        MRF(unaries, [((0, 1), np.zeros((3, 2)))])
    with pytest.raises(ProblemDefinitionError, match="outside 0..2"):
        MRF(unaries, [((0, 3), np.zeros((2, 2)))])
    with pytest.raises(ProblemDefinitionError, match="duplicated"):
        MRF(unaries, [((0, 1), np.zeros((2, 3))), ((1, 0), np.zeros((3, 2)))])
    with pytest.raises(ProblemDefinitionError, match="more than one order-1"):
        MRF(unaries, [((1,), np.zeros(3)), ((1,), np.zeros(3))])
    with pytest.raises(ProblemDefinitionError, match="1 to 3 variables"):
        MRF(unaries + [np.zeros(2)], [((0, 1, 2, 3), np.zeros((2, 3, 2, 2)))])


def test_labelling_outside_the_label_range_is_refused():
    mrf = MRF([np.zeros(2), np.zeros(3)])
    with pytest.raises(ProblemDefinitionError, match="variable 0 the label 2"):
        mrf.energy([2, 0])
    with pytest.raises(ProblemDefinitionError, match="length 2"):
        mrf.energy([0, 0, 0])


def test_too_large_problems_are_refused_with_the_estimate():
    rng = np.random.default_rng(2)
    mrf = MRF.from_triplets(rng.random((6, 8)), [[0, 1, 2], [3, 4, 5]], rng.random((2, 8, 8, 8)))
    with pytest.raises(ResourceLimitError, match=r"would need about .*max_bytes=\.\.\., now 1000"):
        solve(mrf, max_bytes=1000)
    with pytest.raises(ResourceLimitError, match="would need about"):
        solve_ilp(mrf, max_bytes=1000)
    with pytest.raises(ResourceLimitError, match="exceeds max_labellings=1000"):
        exhaustive_search(mrf, max_labellings=1000)
    with pytest.raises(ResourceLimitError, match="Storing the factor tables"):
        MRF([np.zeros(30)] * 3, [((0, 1, 2), np.zeros((30, 30, 30)))], max_bytes=10_000)


@pytest.mark.parametrize(
    ("option", "match"),
    [
        ({"method": "trws"}, "`method` must be one of"),
        ({"max_iter": 0}, "`max_iter`"),
        ({"tol": -1.0}, "`tol`"),
        ({"time_limit": 0}, "`time_limit`"),
    ],
)
def test_bad_solver_options_are_refused(option, match):
    mrf = MRF.from_triplets(np.zeros((3, 2)), [[0, 1, 2]], np.zeros((1, 2, 2, 2)))
    with pytest.raises(ProblemDefinitionError, match=match):
        solve(mrf, **option)


# ----------------------------------------------------------------------------- trees
def test_tree_cover_puts_every_factor_in_one_acyclic_tree():
    rng = np.random.default_rng(3)
    n = 12
    triplets = [list(t) for t in itertools.combinations(range(n), 3)]
    pairs = [list(p) for p in itertools.combinations(range(n), 2)]
    scopes = [triplets[i] for i in rng.permutation(len(triplets))[:120]] + pairs[:30]
    tree = factor_tree_cover(scopes, n)
    assert tree.shape == (len(scopes),)
    for t in np.unique(tree):
        assert is_factor_forest([scopes[f] for f in np.flatnonzero(tree == t)], n)
    # a tree holds at most (n - 1) / 2 triplets: the cover must stay near that bound
    lower = int(np.ceil((120 + 30 / 2) / ((n - 1) / 2)))
    assert lower <= tree.max() + 1 <= 2 * lower


def test_is_factor_forest_detects_a_cycle_through_factors():
    assert is_factor_forest([[0, 1, 2], [2, 3], [3, 4, 5]], 6)
    assert not is_factor_forest([[0, 1, 2], [2, 3], [3, 0]], 4)
    assert not is_factor_forest([[0, 1, 2], [1, 2, 3]], 4)


def test_a_tree_shaped_problem_is_solved_exactly_in_one_iteration():
    """One factor tree: BP is exact, min-marginals included."""
    rng = np.random.default_rng(4)
    labels = [3, 2, 4, 3, 2, 3, 4]
    scopes = [(0, 1, 2), (2, 3), (4, 3, 5), (5, 6)]
    factors = [(s, rng.normal(size=tuple(labels[v] for v in s))) for s in scopes]
    mrf = MRF([rng.normal(size=m) for m in labels], factors)
    exact = exhaustive_search(mrf)
    res = solve(mrf, method="subgradient", tol=0, atol=1e-6, local_search=False)
    assert res.n_trees == 1 and res.n_iter == 1 and res.success
    assert res.energy == pytest.approx(exact.energy, abs=EPS)
    np.testing.assert_allclose(res.min_marginals, exact.min_marginals, atol=EPS)


# ----------------------------------------------------------------------------- exactness
@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(3, 7),
    max_labels=st.integers(2, 4),
    n_pairs=st.integers(0, 6),
    n_triplets=st.integers(0, 6),
    forbid=st.sampled_from([0.0, 0.1]),
    method=st.sampled_from(["srmp", "mplp", "subgradient"]),
)
def test_dual_decomposition_agrees_with_exhaustive_search(
    seed, n, max_labels, n_pairs, n_triplets, forbid, method
):
    rng = np.random.default_rng(seed)
    mrf = random_mixed_problem(rng, n, max_labels, n_pairs, n_triplets, forbid)
    exact = exhaustive_search(mrf)
    if not np.isfinite(exact.energy):
        return  # every labelling forbidden: nothing to compare
    res = solve(mrf, method=method, tol=1e-6, max_iter=300)
    scale = 1.0 + abs(exact.energy)
    assert res.lower_bound <= exact.energy + EPS * scale
    assert res.energy >= exact.energy - EPS * scale
    assert res.energy == pytest.approx(mrf.energy(res.x), abs=1e-9)
    if res.success:
        assert res.energy <= exact.energy + 1e-6 * abs(res.energy) + EPS * scale
    # min-marginals are lower bounds on the constrained minima
    finite = np.isfinite(exact.min_marginals)
    assert np.all(res.min_marginals[finite] <= exact.min_marginals[finite] + EPS * scale)
    assert res.status in (0, 1, 2) and res.success == (res.status == 0)


def planted_problem(rng, n, n_labels, n_cliques):
    """Triplet problem whose planted labelling is cheap everywhere (an easy, tight LP)."""
    truth = rng.integers(0, n_labels, size=n)
    trips = np.array(list(itertools.combinations(range(n), 3)))
    cliques = trips[rng.choice(len(trips), size=n_cliques, replace=False)]
    tables = rng.uniform(0.5, 1.5, size=(n_cliques,) + (n_labels,) * 3).astype(np.float32)
    tables[(np.arange(n_cliques), *truth[cliques].T)] = rng.uniform(0, 0.4, n_cliques)
    unaries = rng.uniform(0, 1, (n, n_labels))
    return MRF.from_triplets(unaries, cliques, tables), truth


@pytest.mark.parametrize("method", ["srmp", "mplp", "subgradient"])
def test_medium_problem_against_highs_ilp_and_lp_bound(method):
    rng = np.random.default_rng(5)
    mrf, _ = planted_problem(rng, 14, 5, 40)
    ilp = solve_ilp(mrf, time_limit=60)
    lp = solve_ilp(mrf, relaxation=True, time_limit=60)
    assert ilp.status == 0 and lp.status == 0
    assert lp.lower_bound <= ilp.energy + 1e-6
    res = solve(mrf, method=method, tol=1e-6, max_iter=400)
    scale = 1.0 + abs(ilp.energy)
    assert res.lower_bound <= lp.lower_bound + EPS * scale
    assert res.energy >= ilp.energy - EPS * scale
    assert res.success
    assert res.energy == pytest.approx(ilp.energy, abs=EPS * scale)


def test_random_hard_problem_bounds_against_lp():
    """Uniform random tables: loose relaxation; the bound still never passes the LP."""
    rng = np.random.default_rng(6)
    n, lab = 10, 3
    trips = np.array(list(itertools.combinations(range(n), 3)))
    cliques = trips[rng.choice(len(trips), size=25, replace=False)]
    mrf = MRF.from_triplets(rng.random((n, lab)), cliques, rng.random((25, lab, lab, lab)))
    lp = solve_ilp(mrf, relaxation=True, time_limit=60)
    exact = exhaustive_search(mrf)
    for method in ("srmp", "mplp", "subgradient"):
        res = solve(mrf, method=method, tol=1e-6, max_iter=300)
        assert res.lower_bound <= lp.lower_bound + EPS
        assert res.lower_bound <= exact.energy + EPS
        assert res.energy >= exact.energy - EPS


def test_ilp_agrees_with_exhaustive_search_with_forbidden_entries():
    rng = np.random.default_rng(7)
    mrf = random_mixed_problem(rng, 6, 3, 4, 4, forbid=0.2)
    exact = exhaustive_search(mrf)
    ilp = solve_ilp(mrf, time_limit=60)
    assert ilp.energy == pytest.approx(exact.energy, abs=1e-6)
    assert np.isfinite(ilp.energy)


@pytest.mark.parametrize("method", ["mplp", "srmp"])
def test_a_warm_start_resumes_the_dual_and_keeps_the_bound_valid(method):
    """Warm-started from a converged dual, one sweep holds its bound (a cold sweep does
    not); with other unaries the bound stays below the exact minimum."""
    rng = np.random.default_rng(11)
    n, lab = 10, 3
    trips = np.array(list(itertools.combinations(range(n), 3)))
    cliques = trips[rng.choice(len(trips), size=25, replace=False)]
    tables = rng.random((25, lab, lab, lab))
    unaries = rng.random((n, lab))
    mrf = MRF.from_triplets(unaries, cliques, tables)
    long = solve(mrf, method=method, tol=0, max_iter=200)
    cold = solve(mrf, method=method, tol=0, max_iter=1)
    warm = solve(mrf, method=method, tol=0, max_iter=1, warm_start=long)
    assert warm.lower_bound >= long.lower_bound - EPS
    assert cold.lower_bound < long.lower_bound - 10 * EPS
    other = MRF.from_triplets(unaries + rng.random((n, lab)), cliques, tables)
    res = solve(other, method=method, tol=0, max_iter=20, warm_start=long)
    exact = exhaustive_search(other)
    assert res.lower_bound <= exact.energy + EPS <= res.energy + 2 * EPS
    assert {k: m.shape for k, m in res.multipliers.items()} == {3: (25, 3, lab)}


def test_a_warm_start_that_does_not_fit_is_refused():
    rng = np.random.default_rng(12)
    cliques = np.array([[0, 1, 2], [1, 2, 3]])
    mrf = MRF.from_triplets(rng.random((4, 3)), cliques, rng.random((2, 3, 3, 3)))
    first = solve(mrf, method="mplp", max_iter=5)
    bigger = MRF.from_triplets(
        rng.random((4, 3)), np.r_[cliques, [[0, 2, 3]]], rng.random((3, 3, 3, 3))
    )
    with pytest.raises(ProblemDefinitionError, match="does not fit"):
        solve(bigger, method="mplp", warm_start=first)
    with pytest.raises(ProblemDefinitionError, match="not 'subgradient'"):
        solve(mrf, method="subgradient", warm_start=first)
    with pytest.raises(ProblemDefinitionError, match="multipliers"):
        solve(mrf, method="mplp", warm_start=solve(mrf, method="subgradient", max_iter=5))


# ----------------------------------------------------------------------------- statuses
def test_iteration_and_time_limits_are_statuses_not_exceptions():
    rng = np.random.default_rng(8)
    n, lab = 9, 4
    cliques = np.array(list(itertools.combinations(range(n), 3)))
    mrf = MRF.from_triplets(
        rng.random((n, lab)), cliques, rng.random((len(cliques), lab, lab, lab))
    )
    for method in ("srmp", "mplp", "subgradient"):
        res = solve(mrf, method=method, max_iter=1, tol=0)
        assert res.status == 1 and not res.success and res.n_iter == 1
        assert res.lower_bound <= res.energy
        res = solve(mrf, method=method, max_iter=10_000, tol=0, time_limit=1e-6)
        assert res.status == 3 and res.n_iter == 1


def test_min_marginal_margin_flags_the_ambiguous_variable():
    """Two near-equal labels on variable 2 only: its margin is the smallest."""
    rng = np.random.default_rng(9)
    mrf, truth = planted_problem(rng, 8, 4, 12)
    unaries = mrf.unaries.copy()
    unaries[2] = 5.0
    unaries[2, truth[2]] = 0.0
    unaries[2, (truth[2] + 1) % 4] = 0.0
    tables = mrf.groups[3].tables.copy()
    has_2 = (mrf.groups[3].scopes == 2).any(axis=1)
    tables[has_2] = 1.0
    mrf = MRF.from_triplets(unaries, mrf.groups[3].scopes, tables)
    res = solve(mrf, tol=1e-6)
    assert res.success
    srt = np.sort(res.min_marginals, axis=1)
    margin = srt[:, 1] - srt[:, 0]
    assert margin[2] == pytest.approx(0.0, abs=EPS)
    assert np.all(np.delete(margin, 2) > 10 * EPS)  # the planted optimum is unique


def test_icm_ends_in_a_local_minimum():
    rng = np.random.default_rng(10)
    mrf = random_mixed_problem(rng, 7, 4, 5, 5)
    res = icm(mrf)
    for i in range(mrf.n_variables):
        for label in range(mrf.n_labels[i]):
            y = res.x.copy()
            y[i] = label
            assert mrf.energy(y) >= res.energy - 1e-9
    assert res.lower_bound == -np.inf and not np.isfinite(res.gap)


def test_sequential_decode_follows_its_rule():
    """Most confident variable first; each takes the label minimising its belief plus every
    factor's smallest reparametrised cost compatible with the labels fixed before it."""
    rng = np.random.default_rng(11)
    mrf = random_mixed_problem(rng, 7, 4, 6, 6)
    big = forbidden_cost(mrf)
    theta = np.minimum(mrf.unaries, big)
    scopes = {k: g.scopes for k, g in mrf.groups.items()}
    tables = {k: working_tables(g.tables, np.arange(len(g)), big) for k, g in mrf.groups.items()}
    lam = {k: rng.normal(size=(len(g), k, mrf.max_labels)) for k, g in mrf.groups.items()}
    belief = beliefs(theta, scopes, lam)

    srt = np.sort(belief, axis=1)
    x = np.full(mrf.n_variables, -1)
    for i in np.argsort(srt[:, 0] - srt[:, 1], kind="stable"):
        cost = belief[i].copy()
        for k, sc in scopes.items():
            for f in np.flatnonzero((sc == i).any(axis=1)):
                for label in range(mrf.max_labels):
                    options = [
                        [label] if v == i else [x[v]] if x[v] >= 0 else range(mrf.max_labels)
                        for v in sc[f]
                    ]
                    cost[label] += min(
                        tables[k][f][y] - sum(lam[k][f, q, y[q]] for q in range(k))
                        for y in itertools.product(*options)
                    )
        x[i] = np.argmin(cost)

    assert np.array_equal(sequential_decode(belief, scopes, tables, lam), x)
