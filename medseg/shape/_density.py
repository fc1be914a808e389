"""Densities of the clique invariants (2-D or 3-D), all stored as Gaussian mixtures.

Every density kind (Gaussian mixture chosen by BIC, single Gaussian, Parzen window) is kept
in one array form: per clique ``K`` weights, means and Cholesky factors of the precisions
(padded to a common ``K`` with zero weight). That makes evaluation one vectorised code path
and persistence a handful of NPZ arrays. Covariances always have ``reg_covar`` added to the
diagonal, so every log-density is finite everywhere.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from sklearn.exceptions import ConvergenceWarning
from sklearn.mixture import GaussianMixture
from sklearn.utils import check_random_state
from threadpoolctl import threadpool_limits

from medseg.errors import ParameterError

__all__ = ["MixtureParams", "fit_mixtures", "mixture_logpdf", "DENSITIES"]

DENSITIES = ("gmm", "gaussian", "parzen")
_LOG_2PI = float(np.log(2.0 * np.pi))


@dataclass
class MixtureParams:
    """Per-clique ``D``-dimensional Gaussian mixtures, padded to ``K`` components.

    Attributes
    ----------
    weights : (C, K) float array
        Mixture weights; padding components have weight 0.
    means : (C, K, D) float array
    precisions_cholesky : (C, K, D, D) float array
        Upper-triangular ``U`` with precision ``U @ U.T`` (scikit-learn's convention).
    n_components : (C,) int array
    """

    weights: np.ndarray
    means: np.ndarray
    precisions_cholesky: np.ndarray
    n_components: np.ndarray

    def subset(self, sl) -> MixtureParams:
        return MixtureParams(
            self.weights[sl], self.means[sl], self.precisions_cholesky[sl], self.n_components[sl]
        )


def _prec_chol_from_cov(cov: np.ndarray) -> np.ndarray:
    """Upper-triangular ``U`` with ``U @ U.T = inv(cov)`` for (D, D) ``cov``."""
    chol = np.linalg.cholesky(cov)
    return np.linalg.solve(chol, np.eye(len(cov))).T


def _fit_gmm(x: np.ndarray, max_components: int, reg_covar: float, rng) -> tuple:
    n_unique = len(np.unique(np.round(x, 12), axis=0))
    best = None
    best_bic = np.inf
    for k in range(1, max(1, min(max_components, n_unique, len(x))) + 1):
        gm = GaussianMixture(
            n_components=k,
            covariance_type="full",
            init_params="k-means++",
            reg_covar=reg_covar,
            random_state=rng.randint(np.iinfo(np.int32).max),
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            gm.fit(x)
        bic = gm.bic(x)
        if bic < best_bic:
            best, best_bic = gm, bic
    return best.weights_, best.means_, best.precisions_cholesky_


def _fit_parzen(x: np.ndarray, reg_covar: float) -> tuple:
    # Gaussian kernels at the samples, bandwidth matrix by Scott's rule (n^(-1/(d+4)))^2 cov
    n, d = x.shape
    cov = np.atleast_2d(np.cov(x.T, bias=False)) if n > 1 else np.zeros((d, d))
    h2 = n ** (-2.0 / (d + 4.0))
    kcov = h2 * cov + reg_covar * np.eye(d)
    u = _prec_chol_from_cov(kcov)
    return np.full(n, 1.0 / n), x.copy(), np.broadcast_to(u, (n, d, d)).copy()


def fit_mixtures(
    samples: np.ndarray,
    *,
    kind: str = "gmm",
    max_components: int = 3,
    reg_covar: float = 1e-5,
    random_state=None,
) -> MixtureParams:
    """Fit one ``D``-dimensional density per clique.

    Parameters
    ----------
    samples : (C, S, D) float array
        Invariant of each clique in each training shape.
    kind : {"gmm", "gaussian", "parzen"}
        ``"gmm"``: Gaussian mixture with 1..``max_components`` components chosen by BIC
        (scikit-learn ``GaussianMixture``, full covariances); ``"gaussian"``: one component;
        ``"parzen"``: a Gaussian kernel on every sample, bandwidth by Scott's rule.
    max_components : int
    reg_covar : float
        Added to the diagonal of every covariance: the floor that keeps a clique whose
        training invariants coincide from producing infinite potentials.
    random_state : int, RandomState instance or None

    Returns
    -------
    MixtureParams
    """
    if kind not in DENSITIES:
        raise ParameterError(f"`density` must be one of {DENSITIES}; got {kind!r}")
    rng = check_random_state(random_state)
    fits = []
    # thousands of tiny problems: BLAS / OpenMP threads only add contention (4x slower)
    with threadpool_limits(limits=1):
        for x in samples:
            if kind == "parzen":
                fits.append(_fit_parzen(x, reg_covar))
            else:
                k = max_components if kind == "gmm" else 1
                fits.append(_fit_gmm(x, k, reg_covar, rng))
    c, dim = len(fits), samples.shape[-1]
    kmax = max(len(f[0]) for f in fits)
    weights = np.zeros((c, kmax))
    means = np.zeros((c, kmax, dim))
    prec = np.tile(np.eye(dim), (c, kmax, 1, 1))
    ncomp = np.zeros(c, dtype=np.int64)
    for i, (w, m, u) in enumerate(fits):
        k = len(w)
        weights[i, :k], means[i, :k], prec[i, :k], ncomp[i] = w, m, u, k
    return MixtureParams(weights, means, prec, ncomp)


def mixture_logpdf(x: np.ndarray, params: MixtureParams) -> np.ndarray:
    """Log-density of each clique's mixture at its own points.

    Parameters
    ----------
    x : (C, P, D) float array
        ``P`` invariant values for each of the ``C`` cliques of ``params``.
    params : MixtureParams
        ``C`` mixtures of dimension ``D``.

    Returns
    -------
    (C, P) float array
        float32 for float32 ``x`` (the potential tables' precision, at about half the
        time), else float64. Finite wherever ``x`` is finite (every covariance is positive
        definite).

    Notes
    -----
    The log-sum-exp over components is accumulated one component at a time, so the memory
    is a few (C, P) arrays whatever the number of components (Parzen windows have one per
    training shape). The Mahalanobis term is written out over the upper-triangular factor, on
    one (C, P) difference plane per dimension: a batched ``(P, D) @ (D, D)`` product per
    clique is slower for the small ``D`` (2 or 3) of the invariants.
    """
    dtype = np.float32 if x.dtype == np.float32 else np.float64
    u = params.precisions_cholesky
    dim = u.shape[-1]
    logdet = np.log(np.diagonal(u, axis1=-2, axis2=-1)).sum(-1)  # (C, K)
    with np.errstate(divide="ignore"):
        logw = np.log(params.weights)  # padding -> -inf
    const = (logdet + logw - 0.5 * dim * _LOG_2PI).astype(dtype)
    u, means = u.astype(dtype), params.means.astype(dtype)
    planes = [np.ascontiguousarray(x[..., i]) for i in range(dim)]
    run_max = None
    run_sum = None
    for k in range(params.weights.shape[1]):
        # |(x - mean) @ U|^2 with U the precision's upper-triangular Cholesky factor
        diff = [planes[i] - means[:, k, i, None] for i in range(dim)]  # D (C, P)
        v = np.zeros(x.shape[:2], dtype=dtype)
        for j in range(dim):
            y = diff[0] * u[:, k, 0, j][:, None]
            for i in range(1, j + 1):
                y += diff[i] * u[:, k, i, j][:, None]
            y *= y
            v += y
        v *= -0.5
        v += const[:, k][:, None]
        if run_max is None:
            run_max, run_sum = v, np.ones_like(v)
            continue
        new_max = np.maximum(run_max, v)
        run_sum = run_sum * np.exp(run_max - new_max) + np.exp(v - new_max)
        run_max = new_max
    return run_max + np.log(run_sum)
