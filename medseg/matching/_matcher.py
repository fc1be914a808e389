"""Dense surface matching in two stages (Zeng et al., CVPR 2010, Sec. 4).

1. Sparse stage: farthest-point samples of A are matched to farthest-point samples of B
   with the third-order energy (descriptor singleton costs; Möbius, orientation and
   geodesic-distortion triplet costs).
2. Dense stage: the Möbius maps of the best matched triplets send every vertex of A to a
   vertex of B; these votes are clustered to their modes, which become the dense candidates;
   the dense energy (vote and descriptor singleton costs, one third-order clique per face
   of A) is minimised by the same dual decomposition.

Departures from the paper in the sparse stage, each measured (session 2, on the FAUST and
TOSCA pairs where session 1 did worst; fraction of sparse matches within 0.1 sqrt(area) of
the truth, four pairs): HKS singletons, 45 targets, random triplets, Möbius + normal
determinant, 100 iterations gave 0.24 / 0.43 / 0.38 / 0.50.

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

Mirror flips (session 3, FAUST). The whole-body left-right flips were not the orientation
term's fault: their sparse labellings were orientation-preserving (their trusted triplets
agreed in orientation with A's as often as the truth's did) and had a lower energy than
the truth's, because they map the body rotated half a turn (left to right and front to
back), which the descriptors, the Möbius and the geodesic terms hardly tell from the truth.
The refinement, started at 8 eigenpairs, then turned these maps into true mirror images,
and turned correct but noisy maps into front-back mirrors (errors near 0.09). Hence:

* :func:`spectral_refine` starts at 16 eigenpairs (keeps orientation; figures there);
* ``n_solves=2``: the sparse stage is solved a second time with the first solution's
  matches excluded; on eight FAUST pairs the two solves were always the truth's basin and
  the half-turn's, and the map with the lower descriptor residual was the right one in all
  eight (residual 0.46-2.94 against 0.78-3.23, one pair within 0.5 %);
* maps that mirror more than half of A (:func:`mirrored_fraction`) are not chosen.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from itertools import combinations

import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree
from sklearn.metrics import pairwise_distances_argmin
from sklearn.utils import check_random_state
from tqdm.auto import tqdm

from medseg.errors import ProblemDefinitionError
from medseg.geometry import (
    GeodesicSolver,
    cotangent_laplacian,
    face_areas,
    geodesic_farthest_point_sampling,
    vertex_areas,
    vertex_normals,
)
from medseg.matching._conformal import conformal_flatten, to_riemann_sphere
from medseg.matching._geometry import (
    heat_kernel_signature,
    laplacian_eigenpairs,
    mirrored_fraction,
    wave_kernel_signature,
)
from medseg.matching._mesh import check_mesh
from medseg.matching._potentials import (
    _canonical_unchecked,
    geodesic_distortion_potentials,
    mobius_potentials,
    orientation_potentials,
    singleton_potentials,
    triplet_potentials,
)
from medseg.matching._solver import MatchingProblem, SolveResult, solve_matching

__all__ = [
    "PreparedSurface",
    "prepare_surface",
    "SurfaceMatch",
    "match_surfaces",
    "spectral_refine",
]

# diffusion times of the HKS on a unit-area surface
_HKS_TIMES = np.geomspace(5e-3, 1.0, 16)
# WKS band on a unit-area surface: from below the first non-zero eigenvalue of elongated
# shapes to Weyl's estimate 4 pi k of the k-th eigenvalue, for k = n_eigen
_WKS_LOWEST = 2.0
_N_WKS = 100


def _standardise(x: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Columns to zero mean and unit variance under the vertex-area weights."""
    w = weights / weights.sum()
    mean = w @ x
    std = np.sqrt(w @ (x - mean) ** 2)
    return (x - mean) / np.maximum(std, 1e-12)


def _descriptor(v, f, evals, evecs, n_eigen):
    """Log HKS (16 times) and log WKS (100 energies), each column standardised, the WKS
    block weighted so that both blocks carry the same total variance."""
    area = vertex_areas(v, f)
    hks = heat_kernel_signature(evals, evecs, times=_HKS_TIMES)
    wks = wave_kernel_signature(
        evals, evecs, n_energies=_N_WKS, energy_range=(_WKS_LOWEST, 4 * np.pi * n_eigen)
    )
    hks = _standardise(np.log(np.maximum(hks, 1e-12)), area)
    wks = _standardise(np.log(np.maximum(wks, 1e-12)), area)
    return np.hstack([hks, wks * np.sqrt(hks.shape[1] / wks.shape[1])])


@dataclass
class PreparedSurface:
    """Everything the matcher computes once per surface (see :func:`prepare_surface`).

    Attributes
    ----------
    vertices : (V, 3) float array
        Centred and scaled to unit total area (so units do not matter).
    faces : (F, 3) int array, outward oriented.
    scale : float
        ``sqrt(area)`` of the input, in its units.
    z : (V,) complex array
        Conformal flattening.
    normals : (V, 3) float array
        Smoothed outward unit normals.
    descriptor : (V, D) float array
        Log heat kernel signature at 16 fixed times and log wave kernel signature at 100
        fixed energies of the unit-area surface, each column standardised over the surface
        (area-weighted), the two blocks with equal weight.
    evals, evecs : (E,), (V, E) float arrays
        Laplace-Beltrami eigenpairs of the unit-area surface.
    samples : (S,) int array
        Geodesic farthest-point samples, in picking order.
    """

    vertices: np.ndarray
    faces: np.ndarray
    scale: float
    z: np.ndarray
    normals: np.ndarray
    descriptor: np.ndarray
    evals: np.ndarray
    evecs: np.ndarray
    samples: np.ndarray
    geodesic: GeodesicSolver = field(repr=False)


def prepare_surface(
    vertices: ArrayLike,
    faces: ArrayLike,
    *,
    name: str = "mesh",
    n_samples: int = 120,
    n_eigen: int = 80,
    random_state=None,
) -> PreparedSurface:
    """Check a mesh and compute its descriptors, flattening, normals and samples.

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (F, 3) int array
    name : str
        Used in error messages.
    n_samples : int
        Farthest-point samples (the sparse points are the first of them).
    n_eigen : int
        Laplace-Beltrami eigenpairs for the HKS.
    random_state : int, RandomState or None

    Returns
    -------
    PreparedSurface
    """
    v, f = check_mesh(vertices, faces, name=name)
    scale = float(np.sqrt(face_areas(v, f).sum()))
    v = (v - v.mean(axis=0)) / scale
    evals, evecs = laplacian_eigenpairs(v, f, n_eigen=n_eigen)
    descriptor = _descriptor(v, f, evals, evecs, n_eigen)
    # smoothed normals: normals of the surface after a short implicit heat flow
    lap, mass = cotangent_laplacian(v, f)
    smooth = splu((mass + 1e-3 * lap).tocsc()).solve(mass @ v)
    normals = vertex_normals(smooth, f)
    geo = GeodesicSolver(v, f)
    samples = geodesic_farthest_point_sampling(
        v, f, n_samples, geodesic=geo, random_state=random_state
    )
    z = conformal_flatten(v, f)
    return PreparedSurface(v, f, scale, z, normals, descriptor, evals, evecs, samples, geo)


@dataclass
class SurfaceMatch:
    """Result of :func:`match_surfaces`.

    Attributes
    ----------
    forward : (V_A,) int array
        0-based index of the vertex of B matched to each vertex of A.
    forward_unrefined : (V_A,) int array
        The dense stage's map before the spectral refinement (the paper's pipeline alone).
    inverse : (V_B,) int array
        For each vertex of B, the vertex of A whose image is nearest to it on B.
    sparse_pairs : (P, 2) int array
        Vertex pairs (A, B) matched by the sparse stage.
    sparse : SolveResult
        Solver outcome of the sparse stage (energy, lower bound, gap, ...).
    dense : SolveResult
        Solver outcome of the dense stage.
    one_to_one_fraction : float
        Fraction of vertices of A matched by the dense solver itself (one-to-one); the rest
        took their best dense candidate.
    mirrored_fraction : float
        Share of A whose image on B is mirrored (:func:`mirrored_fraction`): near 0 for
        an orientation-preserving map, near 1 for a left-right flip.
    solves : list of dict
        Per sparse solve (``n_solves``): ``forward`` (its (V_A,) map), ``mirrored`` (its
        map's mirrored fraction), ``residual`` (area-weighted mean descriptor cost of its
        map, the selection criterion) and ``energy`` (sparse energy).
    timings : dict
        Seconds per step, summed over the solves.
    """

    forward: np.ndarray
    forward_unrefined: np.ndarray
    inverse: np.ndarray
    sparse_pairs: np.ndarray
    sparse: SolveResult
    dense: SolveResult
    one_to_one_fraction: float
    mirrored_fraction: float
    solves: list
    timings: dict


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
    dist_b = np.stack([b.geodesic.distance(j)[tgt] for j in tgt])
    dist_b = 0.5 * (dist_b + dist_b.T)
    k = min(n_candidates, len(tgt))
    # the cost scale of the unconstrained problem, so that a re-solve weighs its terms alike
    scale = max(float(np.median(np.sort(d, axis=1)[:, :k])), 1e-12)
    for ex in map(np.asarray, exclude):
        banned = (ex[:, None] >= 0) & (dist_b[np.maximum(ex, 0)] < opts["exclude_radius"])
        d = np.where(banned, np.inf, d)  # inf marks padding if fewer than k remain
    cand = np.argsort(d, axis=1)[:, :k]  # columns of tgt
    unary = opts["lambda_descriptor"] * np.take_along_axis(d, cand, axis=1) / scale
    dist_a = np.stack([a.geodesic.distance(i)[src] for i in src])
    dist_a = 0.5 * (dist_a + dist_a.T)
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
        log_b = np.stack([b.geodesic.log_map(j)[tgt] for j in tgt])
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
    pos = b.vertices[votes]  # (V_A, T, 3)
    modes = np.zeros((n, n_modes), dtype=np.int64)
    dens = np.zeros((n, n_modes))
    tree = cKDTree(b.vertices)
    for s in range(0, n, chunk):
        p = pos[s : s + chunk]
        d2 = ((p[:, :, None, :] - p[:, None, :, :]) ** 2).sum(-1)
        wv = weights[s : s + chunk]  # (c, T)
        kern = np.exp(-d2 / (2 * radius**2)) * wv[:, None, :]
        density = kern.sum(-1) / wv.sum(axis=1, keepdims=True)  # (c, T)
        alive = np.ones_like(density, dtype=bool)
        for m in range(n_modes):
            score = np.where(alive, density, -1.0)
            j = np.argmax(score, axis=1)
            rows = np.arange(len(p))
            valid = score[rows, j] > 0
            # mode centre: kernel-weighted mean of the votes around the peak
            w = kern[rows, j] * alive
            centre = (w[..., None] * p).sum(1) / np.maximum(w.sum(1), 1e-300)[:, None]
            _, near = tree.query(centre)
            modes[s : s + chunk, m] = np.where(valid, near, modes[s : s + chunk, 0])
            dens[s : s + chunk, m] = np.where(valid, density[rows, j], 0.0)
            alive &= d2[rows, j] > (2 * radius) ** 2
    return modes, dens


def _dense_stage(a, b, modes, dens, *, opts):
    n, k = modes.shape
    # duplicate modes (fewer distinct modes than k) are padded with inf cost
    dup = np.zeros_like(modes, dtype=bool)
    for m in range(1, k):
        dup[:, m] = (modes[:, :m] == modes[:, m : m + 1]).any(axis=1) | (dens[:, m] <= 0)
    desc = singleton_potentials(a.descriptor, b.descriptor, modes)
    desc = desc / max(np.median(desc), 1e-12)
    unary = -np.log(np.maximum(dens, 1e-6)) + opts["lambda_descriptor"] * desc
    unary = np.where(dup, np.inf, unary)
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
    res = solve_matching(problem, max_iter=opts["dense_max_iter"], progress=opts["progress"])
    best = np.argmin(unary, axis=1)
    x = np.where(res.x < k, res.x, best)
    forward = modes[np.arange(n), x]
    return forward, res, float(np.mean(res.x < k))


def spectral_refine(
    forward: ArrayLike,
    evecs_a: ArrayLike,
    mass_a: ArrayLike,
    evecs_b: ArrayLike,
    *,
    k_start: int = 16,
    k_step: int = 4,
) -> np.ndarray:
    """Refine a vertex map by spectral upsampling of its functional map (ZoomOut).

    Parameters
    ----------
    forward : (V_A,) int array
        Vertex of B matched to each vertex of A.
    evecs_a : (V_A, E) float array
        Mass-orthonormal Laplace-Beltrami eigenvectors of A.
    mass_a : (V_A,) float array
        Vertex areas of A.
    evecs_b : (V_B, E) float array
    k_start, k_step : int
        Spectral size of the first functional map, and its increment per iteration, up to E.
        Starting at 8 eigenpairs turned correct but noisy FAUST maps into front-back
        mirrors (mean error 0.041 / 0.071 / 0.088 / 0.077 before, 0.085 / 0.092 / 0.086 /
        0.091 after, with 87-91 % of the faces mirrored); from 16 they refine to 0.018 /
        0.017 / 0.048 / 0.024, and the maps that were already good stay as they were.

    Returns
    -------
    forward : (V_A,) int array

    References
    ----------
    .. [1] Melzi, S., Ren, J., Rodolà, E., Sharma, A., Wonka, P. & Ovsjanikov, M. "ZoomOut:
       spectral upsampling for efficient shape correspondence." ACM TOG 38(6), 2019.
       doi:10.1145/3355089.3356524
    """
    fwd = np.asarray(forward)
    pa = np.asarray(evecs_a, float)
    pb = np.asarray(evecs_b, float)
    mass = np.asarray(mass_a, float)
    n_eig = min(pa.shape[1], pb.shape[1])
    for k in range(k_start, n_eig + 1, k_step):
        # C maps coefficients on B to coefficients on A: Pi Phi_B ~ Phi_A C; the point map
        # is read as in ZoomOut, each row of Phi_A against the rows of Phi_B C^T (reading
        # Phi_A C against Phi_B instead, as session 1 did, assumes C orthonormal: measured on
        # three FAUST / TOSCA pairs, mean error 0.111 / 0.051 / 0.072 against 0.081 / 0.025
        # / 0.073 this way)
        c = pa[:, :k].T @ (mass[:, None] * pb[fwd, :k])
        # exact nearest neighbours by blocked matrix products (a k-d tree in 40-80
        # dimensions is slower)
        fwd = pairwise_distances_argmin(pa[:, :k], pb[:, :k] @ c.T)
    return np.asarray(fwd, dtype=np.int64)


def _choose_solve(mirrored, residual, *, max_mirrored: float) -> int:
    """Index of the solve to keep: among the maps whose mirrored fraction is at most
    ``max_mirrored`` (if none, the least mirrored), the lowest descriptor residual."""
    mirrored = np.asarray(mirrored, float)
    mirrored = np.where(np.isfinite(mirrored), mirrored, 1.0)  # no triangle image: rejected
    ok = mirrored <= max_mirrored
    if not ok.any():
        ok = mirrored == mirrored.min()
    return int(np.argmin(np.where(ok, np.asarray(residual, float), np.inf)))


def _attempt(
    a,
    b,
    *,
    exclude,
    n_sparse,
    n_sparse_targets,
    n_candidates,
    n_triplets,
    n_align,
    n_vote,
    n_modes,
    mode_radius,
    refine,
    mass_a,
    opts,
    rng,
):
    """Sparse stage, dense candidates, dense stage and refinement; the map's mirrored
    fraction."""
    timings = {}
    t0 = time.perf_counter()
    pairs, targets, sparse_res = _sparse_stage(
        a,
        b,
        n_sparse=n_sparse,
        n_targets=n_sparse_targets,
        n_candidates=n_candidates,
        n_triplets=n_triplets,
        n_align=n_align,
        opts=opts,
        rng=rng,
        exclude=exclude,
    )
    timings["sparse"] = time.perf_counter() - t0
    if len(pairs) < 3:
        raise ProblemDefinitionError(
            f"the sparse stage matched only {len(pairs)} points; the surfaces are too "
            "different to be matched (or increase n_candidates)."
        )
    t0 = time.perf_counter()
    trip, cost = _vote_triplets(a, b, pairs, n_vote=n_vote, n_align=n_align, opts=opts, rng=rng)
    votes, weights = _votes(a, b, pairs, trip, cost)
    modes, dens = _modes(b, votes, weights, n_modes=n_modes, radius=mode_radius)
    timings["candidates"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    forward, dense_res, frac = _dense_stage(a, b, modes, dens, opts=opts)
    timings["dense"] = time.perf_counter() - t0
    unrefined = forward
    if refine:
        t0 = time.perf_counter()
        forward = spectral_refine(forward, a.evecs, mass_a, b.evecs)
        timings["refine"] = time.perf_counter() - t0
    return {
        "pairs": pairs,
        "targets": targets,
        "sparse": sparse_res,
        "dense": dense_res,
        "one_to_one": frac,
        "forward": forward,
        "unrefined": unrefined,
        "mirrored": mirrored_fraction(a.vertices, a.faces, b.vertices, b.normals, forward),
        # the dense stage's descriptor cost, area-weighted over A
        "residual": float(
            mass_a @ ((a.descriptor - b.descriptor[forward]) ** 2).sum(axis=1) / mass_a.sum()
        ),
        "timings": timings,
    }


def match_surfaces(
    vertices_a: ArrayLike,
    faces_a: ArrayLike,
    vertices_b: ArrayLike,
    faces_b: ArrayLike,
    *,
    n_sparse: int = 30,
    n_sparse_targets: int = 150,
    n_candidates: int = 6,
    n_triplets: int = 120,
    n_align: int = 150,
    n_vote: int = 100,
    n_modes: int = 3,
    mode_radius: float = 0.05,
    lambda_descriptor: float = 1.0,
    lambda_mobius: float = 1.0,
    lambda_gauss: float = 1.0,
    lambda_geodesic: float = 0.5,
    orientation: str = "intrinsic",
    n_neighbours: int = 5,
    delta: float = 0.2,
    max_iter: int = 300,
    dense_max_iter: int = 30,
    refine: bool = True,
    n_solves: int = 2,
    max_mirrored: float = 0.5,
    exclude_radius: float = 0.1,
    random_state=None,
    progress: bool = False,
) -> SurfaceMatch:
    """Dense vertex-to-vertex correspondence from surface A to surface B.

    Parameters
    ----------
    vertices_a : (V_A, 3) float array
        Surface A; any unit (each surface is scaled to unit area internally, so A and B may
        even be in different units).
    faces_a : (F_A, 3) int array
        Genus-0 triangle mesh (closed, or with holes); see :func:`check_mesh`.
    vertices_b, faces_b : arrays
        Surface B.
    n_sparse : int
        Farthest-point samples of A matched in the sparse stage.
    n_sparse_targets : int
        Farthest-point samples of B they may be matched to.
    n_candidates : int
        Candidates per sparse point (nearest in HKS space).
    n_triplets : int
        Third-order cliques sampled among the sparse points.
    n_align : int
        Samples per surface used to measure a Möbius alignment (mutually closest points).
    n_vote : int
        Best matched triplets whose Möbius maps vote for the dense candidates.
    n_modes : int
        Dense candidates per vertex (modes of its votes).
    mode_radius : float
        Kernel radius of the vote clustering, in units of ``sqrt(area)``.
    lambda_descriptor, lambda_mobius, lambda_gauss : float
        Weights of the singleton, Möbius (dense stage: edge-length distortion) and
        Gaussian-map (orientation) terms.
    lambda_geodesic : float
        Weight of the sparse stage's geodesic-distortion term (0 turns it off).
    orientation : {"intrinsic", "normals"}
        Orientation test of the sparse stage: orientation of geodesic triangles in log maps
        (default), or the paper's sign of the normals' determinant.
    n_neighbours : int
        Geodesic neighbours of each sparse point from which the local cliques are formed.
    delta : float
        Chordal distance on the Riemann sphere under which points pair (Möbius term).
    max_iter, dense_max_iter : int
        Dual-decomposition iterations of the sparse and dense stages.
    refine : bool
        Polish the dense map with :func:`spectral_refine` (ZoomOut), an addition to the
        paper's pipeline. Default True.
    n_solves : int
        Sparse solves, each followed by its own dense stage and refinement. Every solve
        after the first excludes the matches of the earlier ones, so that it settles in
        another basin of the symmetric ambiguity (HKS and WKS cannot tell left from right,
        and on humans hardly front from back). Of the maps that are not mirrored, the one
        whose descriptors agree best (lowest area-weighted mean of the dense stage's
        singleton cost) is returned. 1 turns this off; see Notes.
    max_mirrored : float
        A map whose :func:`mirrored_fraction` exceeds this is a left-right (or front-back)
        flip and is returned only if every solve gave one (then the least mirrored).
    exclude_radius : float
        In a later solve, each sparse point's candidates exclude the targets within this
        geodesic distance (units of ``sqrt(area)``) of its earlier matches.
    random_state : int, RandomState or None
        Farthest-point seeds and the clique sampling.
    progress : bool
        Show tqdm progress of the solvers.

    Returns
    -------
    SurfaceMatch

    Notes
    -----
    Where this differs from the paper, and why:

    * The sparse stage: see the module docstring (descriptor, targets, cliques, geodesic
      and intrinsic orientation terms, each with the measurement that motivated it).
    * Units: each surface is centred and scaled to unit area before anything else, so A
      and B may come in different units (mm and m) without any option; distances in the
      options are in units of ``sqrt(area)``.
    * Dense stage cliques are the faces of A. For a face and a label triplet the third-order
      cost is the squared edge-length distortion (in mean edge lengths) plus
      ``lambda_gauss`` if the image triangle is mirrored against B's normals: a Möbius
      residual per face and label combination would cost ``F (K+1)^3`` alignments.
    * The one-to-one constraint is kept in the dense stage, but a vertex may stay unmatched
      (two independent remeshings have no vertex bijection); unmatched vertices then take
      their best dense candidate, so ``forward`` is complete but not injective.
    * Each Möbius vote is weighted, per vertex, by how well the same map carries the nearby
      matched sparse points (a conformal map fixed by one triplet is accurate only near it).
    * ``refine=True`` adds a ZoomOut pass; ``forward_unrefined`` keeps the map without it.
    * ``n_solves=2`` solves the sparse stage a second time, without the first solution's
      matches, and keeps one of the two maps (not mirrored, best descriptor agreement): on
      bodies with a left-right symmetry the lowest sparse energy is not a reliable guide
      (module docstring, "Mirror flips"). It doubles everything after :func:`prepare_surface`.

    References
    ----------
    .. [1] Zeng, Y., Wang, C., Wang, Y., Gu, X., Samaras, D. & Paragios, N. "Dense non-rigid
       surface registration using high-order graph matching." CVPR 2010.
       doi:10.1109/CVPR.2010.5540189
    .. [2] Lipman, Y. & Funkhouser, T. "Möbius voting for surface correspondence." ACM TOG
       28(3), 2009. doi:10.1145/1531326.1531378
    """
    if n_sparse < 4 or n_sparse_targets < n_sparse or n_candidates < 1:
        raise ProblemDefinitionError(
            "need n_sparse >= 4, n_sparse_targets >= n_sparse and n_candidates >= 1."
        )
    if orientation not in ("intrinsic", "normals"):
        raise ProblemDefinitionError(
            f"orientation must be 'intrinsic' or 'normals', got {orientation!r}."
        )
    if not 0.0 <= max_mirrored <= 1.0 or n_solves < 1 or not exclude_radius > 0:
        raise ProblemDefinitionError(
            "need 0 <= max_mirrored <= 1, n_solves >= 1 and exclude_radius > 0, got "
            f"{max_mirrored}, {n_solves} and {exclude_radius}."
        )
    if n_neighbours < 2:
        raise ProblemDefinitionError(f"n_neighbours must be at least 2, got {n_neighbours}.")
    rng = check_random_state(random_state)
    opts = {
        "lambda_descriptor": lambda_descriptor,
        "lambda_mobius": lambda_mobius,
        "lambda_gauss": lambda_gauss,
        "lambda_geodesic": lambda_geodesic,
        "orientation": orientation,
        "n_neighbours": n_neighbours,
        "delta": delta,
        "max_iter": max_iter,
        "dense_max_iter": dense_max_iter,
        "exclude_radius": exclude_radius,
        "progress": progress,
    }
    timings = {}
    bar = tqdm(total=5, desc="matching", disable=not progress, leave=False)
    t0 = time.perf_counter()
    n_s = max(n_align, n_sparse_targets)
    a = prepare_surface(vertices_a, faces_a, name="surface A", n_samples=n_s, random_state=rng)
    b = prepare_surface(vertices_b, faces_b, name="surface B", n_samples=n_s, random_state=rng)
    timings["prepare"] = time.perf_counter() - t0
    bar.update(1)
    mass_a = vertex_areas(a.vertices, a.faces)
    attempts = []
    for attempt in range(n_solves):
        att = _attempt(
            a,
            b,
            exclude=[t["targets"] for t in attempts],
            n_sparse=n_sparse,
            n_sparse_targets=n_sparse_targets,
            n_candidates=n_candidates,
            n_triplets=n_triplets,
            n_align=n_align,
            n_vote=n_vote,
            n_modes=n_modes,
            mode_radius=mode_radius,
            refine=refine,
            mass_a=mass_a,
            opts=opts,
            rng=rng,
        )
        for step, sec in att["timings"].items():
            timings[step] = timings.get(step, 0.0) + sec
        attempts.append(att)
        bar.update(4 if attempt == 0 else 0)
    bar.close()
    best = attempts[
        _choose_solve(
            [t["mirrored"] for t in attempts],
            [t["residual"] for t in attempts],
            max_mirrored=max_mirrored,
        )
    ]
    forward = best["forward"]
    _, inv = cKDTree(b.vertices[forward]).query(b.vertices)
    return SurfaceMatch(
        forward=forward,
        forward_unrefined=best["unrefined"],
        inverse=np.asarray(inv, dtype=np.int64),
        sparse_pairs=best["pairs"],
        sparse=best["sparse"],
        dense=best["dense"],
        one_to_one_fraction=best["one_to_one"],
        mirrored_fraction=best["mirrored"],
        solves=[
            {
                "forward": t["forward"],
                "mirrored": t["mirrored"],
                "residual": t["residual"],
                "energy": t["sparse"].energy,
            }
            for t in attempts
        ],
        timings=timings,
    )
