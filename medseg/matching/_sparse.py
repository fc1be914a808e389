"""Sparse stage of the matcher (Zeng et al., CVPR 2010, Sec. 4): farthest-point samples of A
matched to farthest-point samples of B with the third-order energy (descriptor singleton
costs; Möbius, orientation and geodesic-distortion triplet costs).

Departures from the paper, each measured (session 2, on the FAUST and TOSCA pairs where
session 1 did worst; fraction of sparse matches within 0.1 sqrt(area) of the truth, four
pairs): HKS singletons, 45 targets, random triplets, Möbius + normal determinant, 100
iterations gave 0.24 / 0.43 / 0.38 / 0.50.

* Singleton descriptor: log HKS (16 times) and log WKS (100 energies), each column
  standardised, blocks weighted equally (the WKS separates points the HKS confuses:
  the true match among the 5 nearest of 45 targets went from 73-87 % to 87-97 %).
* Targets: 150 farthest-point samples of B instead of 1.5 times the sparse points, so the
  true match has a target within about 0.05 sqrt(area) (with 45, the labelling made of the
  targets nearest to the truth had a higher energy than the solver's answer).
* Cliques: half local (a point and two of its geodesic neighbours), half random.
* Triplet cost: ``lambda_mobius`` Möbius term + ``lambda_gauss`` orientation term +
  ``lambda_geodesic`` geodesic-distortion term (:func:`geodesic_distortion_potentials`, an
  isometry prior the paper leaves to the descriptors). With ``orientation="intrinsic"``
  (default) the orientation term compares the orientation of the geodesic triangles read
  in log maps at their corners (:func:`orientation_potentials`), in place of the sign of
  the normals' determinant, which flipped on a third of the true triplets of articulated
  shapes; ``orientation="normals"`` restores the paper's Gaussian-map test.
* 300 subgradient iterations (100 left duality gaps of 0.25-0.5).

Together: 0.83 / 0.93 / 0.90 / 0.83 of sparse matches within 0.1, and a final mean
geodesic error of 0.07 / 0.04 / 0.11 / 0.07 instead of 0.35 / 0.34 / 0.38 / 0.35.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np

from medseg.matching._potentials import (
    geodesic_distortion_potentials,
    orientation_potentials,
    triplet_potentials,
)
from medseg.matching._solver import MatchingProblem, solve_matching


def _sparse_cliques(dist_a, n_triplets, n_neighbours, rng):
    """Third-order cliques among the sparse points: half local (a point and two of its
    ``n_neighbours`` geodesically nearest), half drawn from all triplets."""
    n = len(dist_a)
    near = np.argsort(dist_a, axis=1)[:, 1 : n_neighbours + 1]
    local = {
        tuple(sorted((i, j, k))) for i in range(n) for j, k in combinations(near[i].tolist(), 2)
    }
    local = np.asarray(sorted(local), dtype=np.int64).reshape(-1, 3)
    n_local = min(len(local), n_triplets // 2)
    local = local[np.sort(rng.choice(len(local), n_local, replace=False))]
    all_trip = np.asarray(list(combinations(range(n), 3)), dtype=np.int64)
    pick = rng.choice(len(all_trip), size=min(n_triplets - n_local, len(all_trip)), replace=False)
    return np.unique(np.vstack([local, all_trip[pick]]), axis=0)


def _geodesic_matrix(surface, points):
    """Symmetrised geodesic distances among ``points`` of a prepared surface."""
    dist = np.stack([surface.geodesic.distance(i)[points] for i in points])
    return 0.5 * (dist + dist.T)


def _sparse_stage(
    a, b, *, n_sparse, n_targets, n_candidates, n_triplets, n_align, opts, rng, exclude=()
):
    """Sparse matching. ``exclude``: earlier labellings, each an (n_sparse,) array of target
    columns (-1: unmatched); the targets within ``opts["exclude_radius"]`` (geodesic) of a
    point's earlier matches are removed from its candidates. Returns the vertex pairs, the
    target column of each sparse point (-1: unmatched) and the solver result."""
    src = a.samples[:n_sparse]
    tgt = b.samples[:n_targets]
    d = ((a.descriptor[src][:, None, :] - b.descriptor[tgt][None, :, :]) ** 2).sum(-1)
    dist_b = _geodesic_matrix(b, tgt)
    k = min(n_candidates, len(tgt))
    # the cost scale of the unconstrained problem, so that a re-solve weighs its terms alike
    scale = max(float(np.median(np.sort(d, axis=1)[:, :k])), 1e-12)
    for ex in map(np.asarray, exclude):
        banned = (ex[:, None] >= 0) & (dist_b[np.maximum(ex, 0)] < opts["exclude_radius"])
        d = np.where(banned, np.inf, d)  # inf marks padding if fewer than k remain
    cand = np.argsort(d, axis=1)[:, :k]  # columns of tgt
    unary = opts["lambda_descriptor"] * np.take_along_axis(d, cand, axis=1) / scale
    dist_a = _geodesic_matrix(a, src)
    cliques = _sparse_cliques(dist_a, n_triplets, opts["n_neighbours"], rng)
    grid = np.stack(np.meshgrid(*(np.arange(k),) * 3, indexing="ij"), -1).reshape(-1, 3)
    # labels_col[t, c, p] = cand[cliques[t, p], grid[c, p]]
    labels_col = np.stack([cand[cliques[:, p]][:, grid[:, p]] for p in range(3)], axis=-1)
    intrinsic = opts["orientation"] == "intrinsic"
    costs = triplet_potentials(
        a.z,
        b.z,
        a.normals,
        b.normals,
        src[cliques],
        tgt[labels_col],
        samples_a=a.samples[:n_align],
        samples_b=b.samples[:n_align],
        lambda_mobius=opts["lambda_mobius"],
        lambda_gauss=0.0 if intrinsic else opts["lambda_gauss"],
        delta=opts["delta"],
    )
    if intrinsic and opts["lambda_gauss"]:
        log_a = np.stack([a.geodesic.log_map(i)[src] for i in src])
        # log maps at the targets some candidate list names (the others are never read)
        log_b = np.zeros((len(tgt), len(tgt), 2))
        for j in np.unique(cand):
            log_b[j] = b.geodesic.log_map(tgt[j])[tgt]
        costs = costs + opts["lambda_gauss"] * orientation_potentials(
            log_a, log_b, cliques, labels_col
        )
    if opts["lambda_geodesic"]:
        costs = costs + opts["lambda_geodesic"] * geodesic_distortion_potentials(
            dist_a, dist_b, cliques, labels_col, sigma=0.08
        )
    costs = costs.reshape(len(cliques), k, k, k)
    problem = MatchingProblem(
        unary=unary,
        candidates=cand,
        cliques=cliques,
        clique_costs=costs,
        n_targets=len(tgt),
        unmatched_cost=float(np.max(unary)),
        unmatched_clique_cost=float(np.quantile(costs, 0.5)),
    )
    res = solve_matching(problem, max_iter=opts["max_iter"], progress=opts["progress"])
    ok = res.targets >= 0
    pairs = np.column_stack([src[ok], tgt[res.targets[ok]]])
    return pairs, res.targets, res
