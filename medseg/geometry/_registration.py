"""Point-set registration, used to build landmark correspondences.

On plain arrays of physical points ``(N, 3)`` in mm (the similarity fit itself is
:func:`medseg.geometry.similarity_fit`):

* :func:`principal_frame`: a point cloud's centre, variances and principal axes;
* :func:`principal_axes_candidates`: moment / principal-axes initialisations, one per sign
  choice of the axes (the 4 proper rotations, or all 8 when reflections are allowed);
* :func:`icp_similarity`: iterative closest point with a similarity transform;
* :func:`cpd_nonrigid`: coherent point drift, non-rigid (Myronenko & Song 2010).

References
----------
.. [1] A. Myronenko and X. Song, "Point set registration: coherent point drift", IEEE TPAMI
   32(12), 2010. :doi:`10.1109/TPAMI.2010.46`
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product

import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse.linalg import eigsh
from scipy.spatial import cKDTree

from medseg.geometry._similarity import Similarity, similarity_fit

__all__ = [
    "principal_frame",
    "principal_axes_candidates",
    "icp_similarity",
    "icp_affine",
    "cpd_nonrigid",
    "CPDResult",
]


def principal_frame(points: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre (3,), variances (3,, largest first) and principal axes (3, 3, one per column,
    in the same order; signs arbitrary) of a point cloud."""
    points = np.asarray(points, dtype=float)
    centre = points.mean(axis=0)
    cov = np.cov((points - centre).T)
    evals, evecs = np.linalg.eigh(cov)
    order = np.argsort(evals)[::-1]
    return centre, np.clip(evals[order], 0.0, None), evecs[:, order]


def principal_axes_candidates(
    src: np.ndarray, dst: np.ndarray, *, allow_reflection: bool = False
) -> list[Similarity]:
    """Similarities that put the principal axes of ``src`` onto those of ``dst``.

    The axes of a point cloud are defined up to sign: this returns one transform per sign
    choice, 4 proper rotations (det +1), or 8 if ``allow_reflection``. The scale matches the
    root-mean-square radii of the two clouds.

    Parameters
    ----------
    src, dst : (N, 3), (M, 3) float arrays, mm

    Returns
    -------
    list of Similarity
    """
    c_s, ev_s, e_s = principal_frame(src)
    c_d, ev_d, e_d = principal_frame(dst)
    scale = float(np.sqrt(ev_d.sum() / ev_s.sum())) if ev_s.sum() > 0 else 1.0
    out = []
    for signs in product((1.0, -1.0), repeat=3):
        rot = (e_d * np.asarray(signs)) @ e_s.T
        if not allow_reflection and np.linalg.det(rot) < 0:
            continue
        out.append(Similarity(rotation=rot, scale=scale, translation=c_d - scale * c_s @ rot.T))
    return out


def icp_similarity(
    src: np.ndarray,
    dst: np.ndarray,
    init: Similarity,
    *,
    dst_tree: cKDTree | None = None,
    max_iter: int = 40,
    tol: float = 1e-6,
    allow_reflection: bool = False,
) -> tuple[Similarity, float]:
    """Refine a similarity by symmetric iterative closest points.

    Each iteration pairs every moved ``src`` point with its nearest ``dst`` point and every
    ``dst`` point with its nearest moved ``src`` point, then refits the similarity on both
    pairings; the symmetric pairing stops the scale from collapsing.

    Returns
    -------
    transform : Similarity
    error : float, mm
        Symmetric mean closest-point distance at the end.
    """
    tree_d = dst_tree if dst_tree is not None else cKDTree(dst)
    tf = init
    prev = np.inf
    err = np.inf
    for _ in range(max_iter):
        moved = tf(src)
        d1, i1 = tree_d.query(moved)
        tree_m = cKDTree(moved)
        d2, i2 = tree_m.query(dst)
        err = 0.5 * (d1.mean() + d2.mean())
        if prev - err < tol * max(err, 1e-12):
            break
        prev = err
        pairs_src = np.concatenate([src, src[i2]])
        pairs_dst = np.concatenate([dst[i1], dst])
        tf = similarity_fit(pairs_src, pairs_dst, allow_reflection=allow_reflection)
    return tf, float(err)


def icp_affine(
    src: np.ndarray,
    dst: np.ndarray,
    *,
    dst_tree: cKDTree | None = None,
    max_iter: int = 30,
    tol: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Symmetric ICP with a general affine map, starting from the identity.

    Returns
    -------
    matrix : (3, 3) float array
    translation : (3,) float array
        ``moved = src @ matrix.T + translation``.
    error : float
        Symmetric mean closest-point distance.
    """
    tree_d = dst_tree if dst_tree is not None else cKDTree(dst)
    mat, vec = np.eye(3), np.zeros(3)
    prev, err = np.inf, np.inf
    for _ in range(max_iter):
        moved = src @ mat.T + vec
        d1, i1 = tree_d.query(moved)
        d2, i2 = cKDTree(moved).query(dst)
        err = 0.5 * (d1.mean() + d2.mean())
        if prev - err < tol * max(err, 1e-12):
            break
        prev = err
        a = np.concatenate([src, src[i2]])
        b = np.concatenate([dst[i1], dst])
        sol, *_ = np.linalg.lstsq(np.c_[a, np.ones(len(a))], b, rcond=None)
        mat, vec = sol[:3].T, sol[3]
    return mat, vec, float(err)


@dataclass(frozen=True)
class CPDResult:
    """Outcome of :func:`cpd_nonrigid`: ``warp(points)`` moves any points of the source frame."""

    moved: np.ndarray  # (M, 3) registered source points
    sigma2: float
    n_iter: int
    _y: np.ndarray
    _w: np.ndarray
    _beta: float

    def warp(self, points: np.ndarray) -> np.ndarray:
        """Apply the fitted displacement field ``v(z) = sum_m G(z, y_m) w_m`` to points."""
        points = np.asarray(points, float)
        out = np.empty_like(points)
        step = 4096
        for s in range(0, len(points), step):
            p = points[s : s + step]
            out[s : s + step] = p + np.exp(-_sqdist(p, self._y) / (2.0 * self._beta**2)) @ self._w
        return out


def _sqdist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared Euclidean distances (len(a), len(b)) by one matrix product."""
    d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * (a @ b.T)
    return np.maximum(d2, 0.0, out=d2)


# Smallest exponent of the E-step (exp(-745) underflows to 0; below about -708, subnormal).
_EXP_FLOOR = -700.0


def cpd_nonrigid(
    y: np.ndarray,
    x: np.ndarray,
    *,
    beta: float = 2.0,
    lam: float = 2.0,
    w: float = 0.0,
    max_iter: int = 150,
    tol: float = 1e-3,
    rank: int | None = None,
) -> CPDResult:
    """Coherent point drift, non-rigid: move the source ``y`` onto the target ``x``.

    ``y`` are the Gaussian mixture centroids, displaced by ``G W`` with the Gaussian kernel
    ``G_ij = exp(-|y_i - y_j|^2 / (2 beta^2))``; the EM steps follow [1]_ (fig. 4). With
    ``rank`` the kernel is replaced by its leading eigenpairs and the M-step solved by the
    Woodbury identity, as in the fast variant of [1]_ (section 6).

    Parameters
    ----------
    y : (M, 3) float array
        Source points (moving), in the same units as ``beta``.
    x : (N, 3) float array
        Target points.
    beta : float
        Width of the smoothness kernel (same units as the points).
    lam : float
        Regularisation weight (larger: smoother displacement).
    w : float in [0, 1)
        Weight of the uniform outlier component.
    max_iter, tol
        EM stops when the relative change of ``sigma2`` falls below ``tol``.
    rank : int, optional
        Low-rank kernel approximation (None: exact).
    """
    y = np.asarray(y, float)
    x = np.asarray(x, float)
    m, d = y.shape
    n = x.shape[0]
    g = np.exp(-_sqdist(y, y) / (2.0 * beta**2))
    if rank is not None and rank < m:
        evals, q = eigsh(g, k=rank, which="LA", v0=np.ones(m))  # fixed start: reproducible
        lam_k = np.maximum(evals, 1e-12)
    else:
        q = None
    wmat = np.zeros((m, d))
    ty = y.copy()
    xx = (x * x).sum(1)
    sigma2 = float(_sqdist(y, x).sum() / (d * m * n))
    sigma2 = max(sigma2, 1e-10)
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007
        # p = exp(-|ty_m - x_n|^2 / (2 sigma2)), the exponent built in place on one (M, N)
        # array from the product ty x^T (three times faster than the distances first)
        p = (ty / sigma2) @ x.T
        p -= ((ty * ty).sum(1) / (2.0 * sigma2))[:, None]
        p -= (xx / (2.0 * sigma2))[None, :]
        # floored where exp would underflow: that takes numpy's slow path, and its subnormal
        # results slow every later product; exp(-700) ~ 1e-304 changes no sum
        np.clip(p, _EXP_FLOOR, 0.0, out=p)
        np.exp(p, out=p)
        c = (2.0 * np.pi * sigma2) ** (d / 2.0) * w / (1.0 - w) * m / n
        den = p.sum(axis=0) + c
        p /= np.maximum(den, np.finfo(float).tiny)[None, :]
        p1 = p.sum(axis=1)
        pt1 = p.sum(axis=0)
        px = p @ x
        np_ = pt1.sum()
        # (G + lam sigma2 diag(P1)^-1) W = diag(P1)^-1 PX - Y, multiplied by diag(P1) so
        # that points with no matches (P1 ~ 0) do not make the system singular.
        rhs = px - p1[:, None] * y
        s = lam * sigma2
        if q is None:
            wmat = np.linalg.solve(g * p1[:, None] + s * np.eye(m), rhs)
            ty = y + g @ wmat
        else:
            # Woodbury: (s I + dP1 Q L Q^T)^-1 = (I - dP1 Q (s L^-1 + Q^T dP1 Q)^-1 Q^T) / s
            small = np.diag(s / lam_k) + q.T @ (p1[:, None] * q)
            wmat = (rhs - p1[:, None] * (q @ np.linalg.solve(small, q.T @ rhs))) / s
            ty = y + g @ wmat
        prev = sigma2
        sigma2 = float(
            ((pt1 * xx).sum() - 2.0 * np.einsum("ij,ij->", px, ty) + (p1 * (ty**2).sum(1)).sum())
            / (np_ * d)
        )
        sigma2 = max(sigma2, 1e-10)
        if abs(prev - sigma2) / prev < tol:
            break
    return CPDResult(moved=ty, sigma2=sigma2, n_iter=it, _y=y, _w=wmat, _beta=beta)
