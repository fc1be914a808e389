"""Benchmark medseg.mrf: dual decomposition (subgradient, MPLP) against ICM, HiGHS and pgmax.

Run ``python benchmarks/bench_mrf.py`` for the full table, ``--quick`` for a short run.
Problems are generated here:

* ``random``: uniform random unaries and triplet tables (hard: loose LP relaxation);
* ``pipeline``: the segmentation pipeline's shape without the image parts: a random 3D
  landmark configuration, noisy similar copies as training shapes, one Gaussian density per
  triplet clique of the relative-distance invariant ``(d_ij, d_jk) / (d_ij + d_jk + d_ki)``,
  candidates = the true point plus ``L - 1`` distractors (some near other landmarks), unaries
  = noisy ``-log`` detector probabilities, tables = ``-log`` density of each candidate triplet.

pgmax (loopy max-product) is optional: ``pip install pgmax==0.6.1 jax==0.4.30 jaxlib==0.4.30``;
its column is ``-`` when it is not importable.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time

import numpy as np
from scipy.spatial.transform import Rotation

from medseg.mrf import MRF, icm, solve, solve_ilp


# ----------------------------------------------------------------------------- problems
def random_problem(n, n_labels, n_cliques, rng):
    trips = np.array(list(itertools.combinations(range(n), 3)))
    cl = trips[rng.choice(len(trips), size=min(n_cliques, len(trips)), replace=False)]
    return MRF.from_triplets(
        rng.random((n, n_labels)),
        cl,
        rng.random((len(cl), n_labels, n_labels, n_labels), dtype=np.float32),
    )


def knn_triplets(points, per_landmark, rng):
    """Triplet cliques from each landmark and pairs of its nearest neighbours."""
    n = len(points)
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    k = min(n - 1, max(3, int(np.ceil(np.sqrt(2 * per_landmark))) + 2))
    out = set()
    for i in range(n):
        nb = np.argsort(d[i])[1 : k + 1]
        pairs = list(itertools.combinations(nb.tolist(), 2))
        for j in rng.permutation(len(pairs))[:per_landmark]:
            out.add(tuple(sorted((i,) + pairs[j])))
    return np.array(sorted(out), dtype=np.int64)


def invariant(p_i, p_j, p_k):
    """Relative side lengths (d_ij, d_jk) / (d_ij + d_jk + d_ki); last axis of size 3."""
    dij = np.linalg.norm(p_i - p_j, axis=-1)
    djk = np.linalg.norm(p_j - p_k, axis=-1)
    dki = np.linalg.norm(p_k - p_i, axis=-1)
    s = dij + djk + dki + 1e-12
    return np.stack([dij / s, djk / s], axis=-1)


def ellipsoid_landmarks(n, rng, axes=(20.0, 8.0, 6.0)):
    """``n`` evenly spread points (farthest-point sampling) on an ellipsoid, mm."""
    u = rng.normal(size=(50 * n, 3))
    dense = u / np.linalg.norm(u, axis=1, keepdims=True) * np.asarray(axes)
    picked = [0]
    dist = np.linalg.norm(dense - dense[0], axis=1)
    for _ in range(n - 1):
        picked.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(dense - dense[picked[-1]], axis=1))
    return dense[picked]


def random_similarity(points, rng):
    rot = Rotation.random(random_state=rng).as_matrix()
    return rng.uniform(0.8, 1.25) * points @ rot.T + rng.normal(0, 20, 3)


def pipeline_problem(n, n_labels, per_landmark, rng, *, n_train=30, noise=0.5, alpha=1.0):
    """A problem of the segmentation pipeline's shape; returns (mrf, true labelling)."""
    # landmarks on a hippocampus-sized ellipsoid (mm)
    mean = ellipsoid_landmarks(n, rng)
    train = np.stack(
        [random_similarity(mean + rng.normal(0, noise, mean.shape), rng) for _ in range(n_train)]
    )
    if per_landmark is None:
        cliques = np.array(list(itertools.combinations(range(n), 3)), dtype=np.int64)
    else:
        cliques = knn_triplets(mean, per_landmark, rng)
    i, j, k = cliques.T
    feats = invariant(train[:, i], train[:, j], train[:, k])  # (T, C, 2)
    mu = feats.mean(axis=0)
    cen = feats - mu
    cov = np.einsum("tca,tcb->cab", cen, cen) / (n_train - 1) + 1e-6 * np.eye(2)
    prec = np.linalg.inv(cov)
    logdet = np.linalg.slogdet(cov)[1]

    # test shape, candidates: the truth (jittered) and distractors, shuffled
    test = random_similarity(mean + rng.normal(0, noise, mean.shape), rng)
    cand = np.empty((n, n_labels, 3))
    cand[:, 0] = test + rng.normal(0, 0.3, test.shape)
    n_near = (n_labels - 1) // 3
    others = rng.integers(0, n, size=(n, n_near))
    cand[:, 1 : 1 + n_near] = test[others] + rng.normal(0, 1.0, (n, n_near, 3))
    rest = n_labels - 1 - n_near
    lo, hi = test.min(axis=0) - 5.0, test.max(axis=0) + 5.0
    cand[:, 1 + n_near :] = rng.uniform(lo, hi, (n, rest, 3))
    order = np.argsort(rng.random((n, n_labels)), axis=1)
    cand = np.take_along_axis(cand, order[..., None], axis=1)
    truth = np.argsort(order, axis=1)[:, 0]

    score = rng.normal(0, 1, (n, n_labels))
    score[np.arange(n), truth] += 1.5
    unaries = -(score - np.log(np.exp(score).sum(axis=1, keepdims=True)))

    tables = np.empty((len(cliques), n_labels, n_labels, n_labels), dtype=np.float32)
    step = max(1, 2**22 // n_labels**3)
    for s in range(0, len(cliques), step):
        sl = slice(s, s + step)
        a = cand[i[sl]][:, :, None, None]
        b = cand[j[sl]][:, None, :, None]
        c = cand[k[sl]][:, None, None, :]
        d = invariant(a, b, c) - mu[sl][:, None, None, None]
        m = np.einsum("cxyza,cab,cxyzb->cxyz", d, prec[sl], d)
        tables[sl] = alpha * 0.5 * (m + logdet[sl][:, None, None, None] + 2 * np.log(2 * np.pi))
    return MRF.from_triplets(unaries, cliques, tables), truth


# ----------------------------------------------------------------------------- anchors
def pgmax_available():
    try:
        import pgmax  # noqa: F401
    except Exception:  # ImportError, or a JAX too new for pgmax
        return False
    return True


def run_pgmax(mrf, *, num_iters=200, damping=0.5):
    """Loopy max-product (pgmax, JAX) on the same problem; returns (labelling, seconds)."""
    from pgmax import fgraph, fgroup, infer, vgroup

    t0 = time.perf_counter()
    n, lab = mrf.unaries.shape
    variables = vgroup.NDVarArray(num_states=lab, shape=(n,))
    graph = fgraph.FactorGraph(variable_groups=[variables])
    for k, g in mrf.groups.items():
        configs = np.array(list(itertools.product(range(lab), repeat=k)), dtype=np.int32)
        graph.add_factors(
            fgroup.EnumFactorGroup(
                variables_for_factors=[[variables[int(v)] for v in s] for s in g.scopes],
                factor_configs=configs,
                log_potentials=-g.tables.reshape(len(g), -1),
            )
        )
    bp = infer.build_inferer(graph.bp_state, backend="bp")
    arrays = bp.init(evidence_updates={variables: -mrf.unaries})
    arrays = bp.run(arrays, num_iters=num_iters, damping=damping, temperature=0.0)
    states = infer.decode_map_states(bp.get_beliefs(arrays))
    x = np.asarray(states[variables], dtype=np.int64)
    return x, time.perf_counter() - t0


# ----------------------------------------------------------------------------- runner
HEADER = (
    f"{'problem':<22}{'N':>4}{'L':>4}{'C':>6} {'method':<12}{'time s':>8}{'iter':>6}"
    f"{'ms/it':>7}{'st':>3}"
    f"{'energy':>13}{'lower bd':>13}{'gap':>9}{'E-E_ilp':>10}{'LB-LP':>10}"
)


def fmt(v, spec):
    return format(v, spec) if v is not None and np.isfinite(v) else "-"


def bench_problem(name, mrf, args, rows):
    n, lab = mrf.unaries.shape
    c = mrf.n_factors
    ref_e = lp_bound = None
    cols = mrf.n_variables * lab + sum(len(g) * lab**k for k, g in mrf.groups.items())
    if args.ilp_time_limit > 0 and cols <= args.ilp_max_columns:
        ilp = solve_ilp(mrf, time_limit=args.ilp_time_limit)
        lp = solve_ilp(mrf, relaxation=True, time_limit=args.ilp_time_limit)
        ref_e = ilp.energy if ilp.status == 0 else None
        lp_bound = lp.lower_bound if lp.status == 0 else None
        rows.append(
            (
                name,
                n,
                lab,
                c,
                "HiGHS ILP",
                ilp.time,
                ilp.n_iter,
                ilp.status,
                ilp.energy,
                ilp.lower_bound,
                ilp.gap,
                None,
                None,
            )
        )
        rows.append(
            (
                name,
                n,
                lab,
                c,
                "HiGHS LP",
                lp.time,
                0,
                lp.status,
                lp.energy,
                lp.lower_bound,
                None,
                None,
                None,
            )
        )
        print_row(rows[-2])
        print_row(rows[-1])
    for method in args.methods:
        res = solve(
            mrf, method=method, max_iter=args.max_iter, tol=args.tol, time_limit=args.time_limit
        )
        rows.append(
            (
                name,
                n,
                lab,
                c,
                method,
                res.time,
                res.n_iter,
                res.status,
                res.energy,
                res.lower_bound,
                res.gap,
                None if ref_e is None else res.energy - ref_e,
                None if lp_bound is None else res.lower_bound - lp_bound,
            )
        )
        print_row(rows[-1])
    res = icm(mrf)
    rows.append(
        (
            name,
            n,
            lab,
            c,
            "icm",
            res.time,
            res.n_iter,
            res.status,
            res.energy,
            None,
            None,
            None if ref_e is None else res.energy - ref_e,
            None,
        )
    )
    print_row(rows[-1])
    entries = sum(len(g) * lab**k for k, g in mrf.groups.items())
    if args.pgmax and entries <= args.pgmax_max_entries:
        x, secs = run_pgmax(mrf, num_iters=args.pgmax_iters)
        e = mrf.energy(x)
        rows.append(
            (
                name,
                n,
                lab,
                c,
                "pgmax-bp",
                secs,
                args.pgmax_iters,
                -1,
                e,
                None,
                None,
                None if ref_e is None else e - ref_e,
                None,
            )
        )
        print_row(rows[-1])


def print_row(r):
    name, n, lab, c, method, secs, it, st, e, lb, gap, de, dlb = r
    print(
        f"{name:<22}{n:>4}{lab:>4}{c:>6} {method:<12}{secs:>8.3f}{it:>6}"
        f"{fmt(1e3 * secs / it if it else None, '7.1f'):>7}{st:>3}"
        f"{fmt(e, '13.3f'):>13}{fmt(lb, '13.3f'):>13}{fmt(gap, '9.1e'):>9}"
        f"{fmt(de, '10.3f'):>10}{fmt(dlb, '10.3f'):>10}",
        flush=True,
    )


def suites(quick):
    """(name, builder) pairs; builders take a Generator."""
    if quick:
        return [
            ("pipeline 8/lm", lambda r: pipeline_problem(40, 20, 8, r)[0]),
            ("pipeline 6/lm", lambda r: pipeline_problem(16, 6, 6, r)[0]),
            ("random", lambda r: random_problem(12, 4, 30, r)),
        ]
    out = [
        ("pipeline 8/lm", lambda r: pipeline_problem(40, 20, 8, r)[0]),
        ("pipeline 6/lm", lambda r: pipeline_problem(16, 6, 6, r)[0]),
        ("pipeline 6/lm", lambda r: pipeline_problem(24, 8, 6, r)[0]),
        ("pipeline all triplets", lambda r: pipeline_problem(12, 10, None, r)[0]),
    ]
    out += [
        (f"pipeline N={n}", lambda r, n=n: pipeline_problem(n, 10, 8, r)[0])
        for n in (30, 40, 70, 100)
    ]
    out += [
        (f"pipeline L={lab}", lambda r, lab=lab: pipeline_problem(40, lab, 8, r)[0])
        for lab in (15, 30)
    ]
    out += [(f"pipeline {k}/lm", lambda r, k=k: pipeline_problem(40, 20, k, r)[0]) for k in (5, 10)]
    out += [
        ("pipeline all triplets", lambda r: pipeline_problem(30, 10, None, r)[0]),
        ("pipeline all triplets", lambda r: pipeline_problem(30, 20, None, r)[0]),
        ("random", lambda r: random_problem(12, 4, 30, r)),
        ("random", lambda r: random_problem(40, 10, 320, r)),
    ]
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="three problems, 100 iterations")
    parser.add_argument("--max-iter", type=int, default=None, help="default 500 (100 quick)")
    parser.add_argument("--tol", type=float, default=1e-3, help="relative gap; default 1e-3")
    parser.add_argument(
        "--time-limit", type=float, default=60.0, help="seconds per solve; default 60"
    )
    parser.add_argument(
        "--methods",
        default="srmp,mplp,subgradient",
        help="comma-separated; default srmp,mplp,subgradient",
    )
    parser.add_argument(
        "--ilp-time-limit",
        type=float,
        default=60.0,
        help="seconds per HiGHS ILP and LP solve, 0 to skip; default 60",
    )
    parser.add_argument(
        "--ilp-max-columns",
        type=int,
        default=400_000,
        help="skip HiGHS above this many LP columns; default 400000",
    )
    parser.add_argument(
        "--no-pgmax",
        dest="pgmax",
        action="store_false",
        help="skip pgmax even when it is importable",
    )
    parser.add_argument("--pgmax-iters", type=int, default=200, help="default 200")
    parser.add_argument(
        "--pgmax-max-entries",
        type=int,
        default=3_000_000,
        help="skip pgmax above this many table entries; default 3000000",
    )
    parser.add_argument("--seed", type=int, default=0, help="default 0")
    parser.add_argument(
        "--only", default="", help="run only the problems whose name contains this text"
    )
    args = parser.parse_args(argv)
    args.methods = [m for m in args.methods.split(",") if m]
    args.max_iter = args.max_iter or (100 if args.quick else 500)
    if args.pgmax and not pgmax_available():
        print("pgmax not importable: its rows are skipped", file=sys.stderr)
        args.pgmax = False
    print(
        f"max_iter={args.max_iter} tol={args.tol} seed={args.seed}; status: 0 gap closed, "
        "1 iteration limit, 2 stagnation, 3 time limit; times include setup"
    )
    print(HEADER)
    rows = []
    for name, build in suites(args.quick):
        if args.only not in name:
            continue
        t0 = time.perf_counter()
        mrf = build(np.random.default_rng(args.seed))
        print(f"# {name}: {mrf!r}, generated in {time.perf_counter() - t0:.1f} s", flush=True)
        bench_problem(name, mrf, args, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
