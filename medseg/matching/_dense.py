"""Dense stage of the matcher (Zeng et al., CVPR 2010, Sec. 4): every vertex of A chooses
among its dense candidates (the modes of its Möbius votes, :mod:`medseg.matching._voting`).

The singleton cost is the vote density (as a negative log) plus the descriptor cost; the
cliques are the faces of A, each costing the squared edge-length distortion of its image
plus ``lambda_gauss`` if the image triangle is mirrored against B's normals.

Without the one-to-one constraint (default), the energy is a third-order MRF on A's faces,
minimised by block-coordinate dual ascent (:func:`solve_many_to_one`), which certifies its
labelling. With it (``dense_one_to_one=True``, the paper's formulation), by the sparse stage's
dual decomposition, vertices allowed to stay unmatched.

Why not one-to-one (session 4, FAUST tr_reg_010 -> tr_reg_012): A and B are remeshed
independently, and each vertex's candidates are the modes of its votes, which lie at least
``2 mode_radius`` apart, so two neighbours of A whose best mode is the same vertex of B
cannot both keep it; the other candidate is another basin. Every vertex on its best
candidate costs 28,000; under the constraint the dual bound was 238,000 after the default 30
iterations, 317,000 after 300, with the best labelling at 410,000 (37 % unmatched): the
gap of 0.45 was the constraint fighting the data. Many-to-one, the dual converges to a gap
under 1e-3 in 80 sweeps (0.3 s); the final map is the same after the refinement.
"""

from __future__ import annotations

import numpy as np

from medseg.geometry import face_areas
from medseg.matching._potentials import singleton_potentials
from medseg.matching._solver import MatchingProblem, solve_many_to_one, solve_matching


def _dense_unary(a, b, modes, dens, *, opts) -> np.ndarray:
    """(V_A, K) singleton costs of the candidates ``modes`` (vertices of B) with vote
    densities ``dens`` (0: missing mode): the vote density as a negative log plus the
    descriptor cost; inf on duplicate and missing modes."""
    k = modes.shape[1]
    dup = np.zeros_like(modes, dtype=bool)
    for m in range(1, k):
        dup[:, m] = (modes[:, :m] == modes[:, m : m + 1]).any(axis=1) | (dens[:, m] <= 0)
    desc = singleton_potentials(a.descriptor, b.descriptor, modes)
    desc = desc / max(np.median(desc), 1e-12)
    unary = -np.log(np.maximum(dens, 1e-6)) + opts["lambda_descriptor"] * desc
    return np.where(dup, np.inf, unary)


def _best_candidates(a, b, modes, dens, *, opts) -> np.ndarray:
    """The (V_A,) map of each vertex's cheapest candidate (:func:`_dense_unary`): the
    sparse stage and the Möbius votes without the dense stage."""
    best = np.argmin(_dense_unary(a, b, modes, dens, opts=opts), axis=1)
    return modes[np.arange(len(modes)), best]


def _dense_stage(a, b, modes, dens, *, opts):
    """Dense matching among the (V_A, K) candidate vertices ``modes`` of B, with vote
    densities ``dens`` (0: missing mode). Returns the (V_A,) map, the solver result, the
    (V_A,) mask of the vertices the solver matched (the rest take their best candidate in
    the map) and the map of best candidates (the votes alone, for ablations)."""
    n, k = modes.shape
    unary = _dense_unary(a, b, modes, dens, opts=opts)
    f = a.faces
    labels = modes[f]  # (F, 3, k)
    q = b.vertices
    p = a.vertices
    h = np.sqrt(face_areas(p, f).mean() * 4 / np.sqrt(3))  # mean edge length
    cost = np.zeros((len(f), k, k, k))
    ii, jj, kk = np.meshgrid(np.arange(k), np.arange(k), np.arange(k), indexing="ij")
    qi = q[labels[:, 0][:, ii]]  # (F, k, k, k, 3)
    qj = q[labels[:, 1][:, jj]]
    qk = q[labels[:, 2][:, kk]]
    for (u, pu), (w, pw) in (
        ((qi, p[f[:, 0]]), (qj, p[f[:, 1]])),
        ((qj, p[f[:, 1]]), (qk, p[f[:, 2]])),
        ((qk, p[f[:, 2]]), (qi, p[f[:, 0]])),
    ):
        la = np.linalg.norm(pu - pw, axis=1)[:, None, None, None]
        lb = np.linalg.norm(u - w, axis=-1)
        cost += ((lb - la) / h) ** 2
    # orientation of the image triangle against B's normals: mirror flips cost lambda_gauss
    nrm = np.cross(qj - qi, qk - qi)
    nb = (b.normals[labels[:, 0][:, ii]] + b.normals[labels[:, 1][:, jj]]) + b.normals[
        labels[:, 2][:, kk]
    ]
    flipped = np.einsum("...c,...c->...", nrm, nb) < 0
    cost = opts["lambda_mobius"] * np.minimum(cost, 50.0) + opts["lambda_gauss"] * flipped
    problem = MatchingProblem(
        unary=unary,
        candidates=modes,
        cliques=f,
        clique_costs=cost,
        n_targets=len(q),
        unmatched_cost=float(np.quantile(unary[np.isfinite(unary)], 0.95)),
        unmatched_clique_cost=float(np.quantile(cost, 0.9)),
    )
    if opts["dense_one_to_one"]:
        res = solve_matching(problem, max_iter=opts["dense_max_iter"], progress=opts["progress"])
    else:
        res = solve_many_to_one(problem, max_iter=opts["dense_max_iter"], progress=opts["progress"])
    best = np.argmin(unary, axis=1)
    x = np.where(res.x < k, res.x, best)
    forward = modes[np.arange(n), x]
    return forward, res, res.x < k, modes[np.arange(n), best]
