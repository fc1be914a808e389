"""Dense candidates from Möbius voting (Lipman & Funkhouser 2009, as Zeng et al. use it).

The matched sparse pairs give triplets; the Möbius maps of the triplets that align the
flattened surfaces best each send every vertex of A to a vertex of B (a vote), weighted by
how well the same map carries the nearby sparse pairs. Each vertex's votes are clustered to
their modes, which become its candidates in the dense stage (:mod:`medseg.matching._dense`).
"""

from __future__ import annotations

from itertools import combinations

import numpy as np
from scipy.spatial import cKDTree

from medseg.matching._conformal import to_riemann_sphere
from medseg.matching._potentials import _canonical_unchecked, mobius_potentials


def _vote_triplets(a, b, pairs, *, n_vote, n_align, opts, rng):
    """The ``n_vote`` matched triplets whose Möbius maps align the surfaces best."""
    idx = np.asarray(list(combinations(range(len(pairs)), 3)))
    if len(idx) > 1500:
        idx = idx[np.sort(rng.choice(len(idx), 1500, replace=False))]
    cost = mobius_potentials(
        a.z,
        b.z,
        pairs[idx, 0],
        pairs[idx, 1][:, None, :],
        samples_a=a.samples[:n_align],
        samples_b=b.samples[:n_align],
        delta=opts["delta"],
    )[:, 0]
    order = np.argsort(cost)[:n_vote]
    return idx[order], cost[order]


def _votes(a, b, pairs, trip, cost, *, sigma_local=0.15, sigma_error=0.05):
    """Every vertex of A sent to B by each triplet's Möbius map.

    Returns (V_A, T) targets and (V_A, T) weights. A conformal map fixed by one triplet is
    accurate only in part of the surface, so each vote is weighted by how well the same map
    carries the matched sparse points near that vertex onto their partners (geodesic
    Gaussian window of width ``sigma_local`` on A, error scale ``sigma_error`` on B, both in
    units of sqrt(area)), in the spirit of blended intrinsic maps (Kim et al. 2011).
    """
    m_a, _ = _canonical_unchecked(a.z[pairs[trip, 0]])
    m_b, _ = _canonical_unchecked(b.z[pairs[trip, 1]])
    targets = np.empty((len(a.z), len(trip)), dtype=np.int64)
    for t in range(len(trip)):
        sa = to_riemann_sphere(a.z, m_a[t])
        sb = to_riemann_sphere(b.z, m_b[t])
        _, targets[:, t] = cKDTree(sb).query(sa)
    # (P, T): how far each triplet's map sends each sparse point from its partner
    miss = np.linalg.norm(
        b.vertices[targets[pairs[:, 0]]] - b.vertices[pairs[:, 1]][:, None], axis=-1
    )
    good = np.exp(-0.5 * (miss / sigma_error) ** 2)
    dist = np.stack([a.geodesic.distance(s) for s in pairs[:, 0]], axis=1)  # (V_A, P)
    window = np.exp(-0.5 * (dist / sigma_local) ** 2) + 1e-12
    weights = (window @ good) / window.sum(axis=1, keepdims=True)
    return targets, weights + 1e-9


def _modes(b, votes, weights, *, n_modes, radius, chunk=256):
    """Weighted mean-shift-like modes of each vertex's votes, as B vertices; (V_A, n_modes)
    targets and their vote densities (0 for missing modes)."""
    n, t = votes.shape
    # single precision: squared distances to 1e-7 of radius^2 are plenty for a kernel
    pos = b.vertices.astype(np.float32)[votes]  # (V_A, T, 3)
    inv_2r2 = np.float32(1.0 / (2 * radius**2))
    modes = np.zeros((n, n_modes), dtype=np.int64)
    dens = np.zeros((n, n_modes))
    tree = cKDTree(b.vertices)
    for s in range(0, n, chunk):
        p = pos[s : s + chunk]
        sq = (p**2).sum(-1)
        # squared distances among each vertex's votes by one batched product
        d2 = np.maximum(sq[:, :, None] + sq[:, None, :] - 2 * np.matmul(p, p.transpose(0, 2, 1)), 0)
        wv = weights[s : s + chunk].astype(np.float32)  # (c, T)
        kern = np.exp(-d2 * inv_2r2) * wv[:, None, :]
        density = kern.sum(-1) / wv.sum(axis=1, keepdims=True)  # (c, T)
        alive = np.ones_like(density, dtype=bool)
        for m in range(n_modes):
            score = np.where(alive, density, -1.0)
            j = np.argmax(score, axis=1)
            rows = np.arange(len(p))
            valid = score[rows, j] > 0
            # mode centre: kernel-weighted mean of the votes around the peak
            w = kern[rows, j] * alive
            centre = np.matmul(w[:, None, :], p)[:, 0] / np.maximum(w.sum(1), 1e-30)[:, None]
            _, near = tree.query(centre)
            modes[s : s + chunk, m] = np.where(valid, near, modes[s : s + chunk, 0])
            dens[s : s + chunk, m] = np.where(valid, density[rows, j], 0.0)
            alive &= d2[rows, j] > (2 * radius) ** 2
    return modes, dens


def _dense_candidates(a, b, pairs, *, n_vote, n_align, n_modes, radius, opts, rng):
    """(V_A, n_modes) candidate vertices of B for every vertex of A, and their vote
    densities (0: missing mode), from the matched sparse ``pairs``."""
    trip, cost = _vote_triplets(a, b, pairs, n_vote=n_vote, n_align=n_align, opts=opts, rng=rng)
    votes, weights = _votes(a, b, pairs, trip, cost)
    return _modes(b, votes, weights, n_modes=n_modes, radius=radius)
