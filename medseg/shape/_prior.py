"""The pose-invariant triplet shape prior of Wang et al. (MICCAI 2010).

One estimator, :class:`TripletPrior`: its parameter table, ``fit`` (cliques, invariants,
densities) and the potentials for one configuration or whole candidate tables. Over 400
lines because the potential tables are built here chunk by chunk under a memory budget;
the pieces it composes (invariants, cliques, densities, the file mapping) have modules of
their own.
"""

from __future__ import annotations

import numbers
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from sklearn.base import BaseEstimator
from sklearn.utils import check_random_state

from medseg.errors import CohortError, NotFittedError, ParameterError
from medseg.geometry import procrustes_mean
from medseg.io import load_arrays, save_arrays
from medseg.memory import (
    BYTES_PER_TRIPLE,
    check_memory,
    format_bytes,
    memory_limit_bytes,
    potential_chunk_cliques,
    potential_table_bytes,
)
from medseg.shape._cliques import _METHODS, clique_table_size, select_cliques
from medseg.shape._density import DENSITIES, MixtureParams, fit_mixtures, mixture_logpdf
from medseg.shape._invariants import INVARIANTS
from medseg.shape._persistence import prior_from_state, prior_state

__all__ = ["TripletPrior", "MIN_TRAINING_SHAPES"]

#: fewest training shapes :meth:`TripletPrior.fit` accepts (a covariance needs spread)
MIN_TRAINING_SHAPES = 3


def _in(options):
    return lambda v: v in options, f"one of {options}"


def _positive_int():
    return (
        lambda v: isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= 1,
        "a positive integer",
    )


def _positive_real():
    return (
        lambda v: isinstance(v, numbers.Real) and not isinstance(v, bool) and np.isfinite(v)
        and v > 0,
        "a positive finite number",
    )  # fmt: skip


def _cliques_ok(v):
    if isinstance(v, str):
        return v in _METHODS
    arr = np.asarray(v)
    return arr.ndim == 2 and arr.shape[1] == 3 and np.issubdtype(arr.dtype, np.integer)


# the constraint table: parameter -> (check, what it must be)
_PARAMETER_CONSTRAINTS = {
    "cliques": (_cliques_ok, f"one of {_METHODS} or a (C, 3) integer array"),
    "density": _in(DENSITIES),
    "invariant": _in(tuple(INVARIANTS)),
    "alpha": _positive_real(),
    "max_components": _positive_int(),
    "reg_covar": _positive_real(),
    "n_neighbors": (
        lambda v: isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= 2,
        "an integer >= 2",
    ),
    "max_cliques": (
        lambda v: v is None or (isinstance(v, numbers.Integral) and v >= 1),
        "None or a positive integer",
    ),
}


def _table_hint(n_cliques: int, n_lab: int, chunk_bytes: int, limit: int | None) -> str:
    """The largest L (at this C) and C (at this L) whose tables fit under the limit."""
    limit = memory_limit_bytes() if limit is None else limit
    fit_l = next(
        (lab for lab in range(n_lab - 1, 0, -1)
         if potential_table_bytes(n_cliques, lab, chunk_bytes=chunk_bytes) <= limit),
        0,
    )  # fmt: skip
    # the most cliques whose tables and chunk of working memory fit (monotone in C)
    lo, hi = 0, n_cliques - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if potential_table_bytes(mid, n_lab, chunk_bytes=chunk_bytes) <= limit:
            lo = mid
        else:
            hi = mid - 1
    fit_c = lo
    ways = []
    if fit_l >= 1:
        ways.append(
            f"use at most {fit_l} candidates per landmark (now {n_lab}; the tables grow as L^3)"
        )
    if fit_c >= 1:
        ways.append(
            f"at most {fit_c} cliques (now {n_cliques}: a sparser set, "
            "cliques='knn' or 'delaunay', or max_cliques=...)"
        )
    if not ways:
        return (
            f"the limit is below the tables of even one candidate or one clique "
            f"({format_bytes(4 * n_lab**3)} per clique); raise it"
        )
    return ", or ".join(ways)


class TripletPrior(BaseEstimator):
    """Pose-invariant higher-order shape prior on triplets of landmarks.

    For each clique ``c = (i, j, k)`` the invariant ``d_c`` of the triangle (relative side
    lengths, or two of its angles) is unchanged by translation, rotation and uniform scaling
    of the shape, so the training shapes need no alignment. A density ``psi_c`` of ``d_c`` is
    learned per clique, and the clique potential is ``H_c(x_c) = -alpha log psi_c(d_c(x_c))``.

    Parameters
    ----------
    cliques : {"delaunay", "knn", "all"} or (C, 3) int array, default "delaunay"
        How to choose the cliques on the mean training shape (see :func:`select_cliques`),
        or the cliques themselves.
    density : {"gmm", "gaussian", "parzen"}, default "gmm"
        Gaussian mixture with components chosen by BIC, one Gaussian, or a Parzen window.
    invariant : {"distance", "distance_size", "angle"}, default "distance"
        :func:`relative_distances` (the paper's, 2-D), :func:`relative_distances_and_size`
        (3-D: also the log perimeter, so only the scales of the training population fit)
        or :func:`triangle_angles` (2-D).
    alpha : float, default 1.0
        Weight of the prior in the potentials.
    max_components : int, default 3
        Largest mixture size tried by BIC (``density="gmm"``).
    reg_covar : float, default 1e-5
        Added to every covariance diagonal (units of the invariant squared): a floor that
        keeps every potential finite, even for a clique whose training invariants coincide.
        The default allows a standard deviation of about 0.003 in relative distance.
    n_neighbors : int, default 4
        Neighbours per landmark when ``cliques="knn"``.
    max_cliques : int or None, default None
        Keep at most this many cliques (a random subset).
    random_state : int, RandomState instance or None
        Seeds the mixture initialisations and any clique subsampling.

    Attributes
    ----------
    n_landmarks_ : int
        N.
    mean_shape_ : (N, 3) float array, mm
        Generalised Procrustes mean of the training shapes (used to choose the cliques).
    cliques_ : (C, 3) int64 array
        Sorted rows ``i < j < k``.
    n_components_ : (C,) int array
        Mixture components per clique.
    weights_ : (C, K) float array
        Mixture weights (padding components have weight 0).
    means_ : (C, K, D) float array
        Component means, in the units of the invariant.
    precisions_cholesky_ : (C, K, D, D) float array
        Upper-triangular Cholesky factors of the component precisions.
    n_training_shapes_ : int

    References
    ----------
    .. [1] C. Wang, O. Teboul, F. Michel, S. Essafi, N. Paragios, "3D knowledge-based
       segmentation using pose-invariant higher-order graphs", MICCAI 2010.
       :doi:`10.1007/978-3-642-15711-0_24`

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> base = rng.normal(size=(8, 3)) * 10
    >>> shapes = base + rng.normal(scale=0.3, size=(20, 8, 3))
    >>> prior = TripletPrior(random_state=0).fit(shapes)
    >>> prior.clique_potentials(shapes[0]).shape == (len(prior.cliques_),)
    True
    """

    FORMAT = "medseg.shape.TripletPrior"
    FORMAT_VERSION = 1

    def __init__(
        self,
        *,
        cliques="delaunay",
        density: str = "gmm",
        invariant: str = "distance",
        alpha: float = 1.0,
        max_components: int = 3,
        reg_covar: float = 1e-5,
        n_neighbors: int = 4,
        max_cliques: int | None = None,
        random_state=None,
    ):
        self.cliques = cliques
        self.density = density
        self.invariant = invariant
        self.alpha = alpha
        self.max_components = max_components
        self.reg_covar = reg_covar
        self.n_neighbors = n_neighbors
        self.max_cliques = max_cliques
        self.random_state = random_state

    # ------------------------------------------------------------------ validation
    def _validate_params(self) -> None:
        for name, (check, what) in _PARAMETER_CONSTRAINTS.items():
            value = getattr(self, name)
            if not check(value):
                raise ParameterError(
                    f"TripletPrior parameter `{name}` must be {what}; got {value!r}"
                )

    def _check_fitted(self) -> None:
        if not hasattr(self, "cliques_"):
            raise NotFittedError(
                "this TripletPrior is not fitted yet: call fit(shapes) or TripletPrior.load(path)"
            )

    def _check_points(self, points: ArrayLike, name: str) -> np.ndarray:
        pts = np.asarray(points, dtype=float)
        if pts.ndim < 2 or pts.shape[-2:] != (self.n_landmarks_, 3):
            raise ParameterError(
                f"`{name}` must have shape (..., {self.n_landmarks_}, 3) (the prior was fitted "
                f"on {self.n_landmarks_} landmarks); got {pts.shape}"
            )
        if not np.all(np.isfinite(pts)):
            raise ParameterError(f"`{name}` contains NaN or infinite coordinates")
        return pts

    # ------------------------------------------------------------------ fitting
    def fit(self, shapes: ArrayLike, y=None) -> TripletPrior:
        """Learn the clique densities from training landmark configurations.

        Parameters
        ----------
        shapes : (S, N, 3) float array, mm
            Landmarks in correspondence, each shape in its own pose (no alignment needed).
        y : ignored

        Returns
        -------
        self
        """
        self._validate_params()
        shapes = np.asarray(shapes, dtype=float)
        if shapes.ndim != 3 or shapes.shape[2] != 3 or shapes.shape[1] < 3:
            raise ParameterError(
                f"`shapes` must have shape (S, N, 3) with N >= 3 landmarks; got {shapes.shape}"
            )
        if not np.all(np.isfinite(shapes)):
            raise ParameterError("`shapes` contains NaN or infinite coordinates")
        if shapes.shape[0] < MIN_TRAINING_SHAPES:
            raise CohortError(
                f"the shape prior needs at least {MIN_TRAINING_SHAPES} training shapes to "
                f"estimate a density per clique; got {shapes.shape[0]}. Add training cases."
            )
        rng = check_random_state(self.random_state)
        n = shapes.shape[1]
        mean = procrustes_mean(shapes)
        if isinstance(self.cliques, str):
            cliques = select_cliques(
                mean,
                method=self.cliques,
                k=self.n_neighbors,
                max_cliques=self.max_cliques,
                random_state=rng,
            )
        else:
            cliques = np.unique(np.sort(np.asarray(self.cliques, dtype=np.int64), 1), axis=0)
            bad = (cliques[:, 0] == cliques[:, 1]) | (cliques[:, 1] == cliques[:, 2])
            if cliques.size == 0 or bad.any() or cliques.min() < 0 or cliques.max() >= n:
                raise ParameterError(
                    f"`cliques` must hold triples of distinct landmark indices in [0, {n}); "
                    "got an empty array, a repeated index or an index out of range"
                )
        samples = self._invariants(shapes[:, cliques])  # (S, C, D)
        params = fit_mixtures(
            np.ascontiguousarray(samples.transpose(1, 0, 2)),
            kind=self.density,
            max_components=self.max_components,
            reg_covar=self.reg_covar,
            random_state=rng,
        )
        self.n_landmarks_ = n
        self.n_training_shapes_ = shapes.shape[0]
        self.mean_shape_ = mean
        self.cliques_ = cliques
        self._set_mixtures(params)
        return self

    def _set_mixtures(self, params: MixtureParams) -> None:
        self.weights_ = params.weights
        self.means_ = params.means
        self.precisions_cholesky_ = params.precisions_cholesky
        self.n_components_ = params.n_components

    def _mixtures(self) -> MixtureParams:
        return MixtureParams(
            self.weights_, self.means_, self.precisions_cholesky_, self.n_components_
        )

    def _invariants(self, triangles: np.ndarray) -> np.ndarray:
        """(..., 3, 3) triangles -> (..., D) invariant."""
        pi, pj, pk = triangles[..., 0, :], triangles[..., 1, :], triangles[..., 2, :]
        d_ij = np.linalg.norm(pi - pj, axis=-1)
        d_jk = np.linalg.norm(pj - pk, axis=-1)
        d_ki = np.linalg.norm(pk - pi, axis=-1)
        return INVARIANTS[self.invariant](d_ij, d_jk, d_ki)

    # ------------------------------------------------------------------ potentials
    def clique_potentials(self, points: ArrayLike) -> np.ndarray:
        """Potentials ``H_c`` of every clique for one landmark configuration.

        Parameters
        ----------
        points : (N, 3) or (B, N, 3) float array, mm
            Landmark positions, any pose.

        Returns
        -------
        (C,) or (B, C) float64 array
            ``-alpha log psi_c(d_c(x_c))``; always finite (lower is more plausible; may be
            negative where the density exceeds 1).
        """
        self._check_fitted()
        pts = self._check_points(points, "points")
        batch = pts.reshape(-1, self.n_landmarks_, 3)
        inv = self._invariants(batch[:, self.cliques_])  # (B, C, D)
        logp = mixture_logpdf(np.ascontiguousarray(inv.transpose(1, 0, 2)), self._mixtures())
        out = -self.alpha * logp.T  # (B, C)
        return out.reshape(pts.shape[:-2] + (len(self.cliques_),))

    def score_samples(self, shapes: ArrayLike) -> np.ndarray:
        """Total log prior ``sum_c log psi_c`` of each configuration, shape (B,) or scalar."""
        return -self.clique_potentials(shapes).sum(axis=-1) / self.alpha

    def table_size(self, n_candidates: int):
        """Count and memory of the potential tables for ``n_candidates`` per landmark.

        Returns
        -------
        CliqueTableSize
        """
        self._check_fitted()
        return clique_table_size(self.cliques_, n_candidates)

    def potential_tables(
        self,
        candidates: ArrayLike,
        *,
        chunk_size: int | None = None,
        max_bytes: int = 256 * 2**20,
        max_table_bytes: int | None = None,
    ) -> np.ndarray:
        """Potentials of every candidate triple of every clique.

        Parameters
        ----------
        candidates : (N, L, 3) float array, mm
            ``L`` candidate positions for each landmark.
        chunk_size : int, optional
            Cliques evaluated together; default: as many as fit in ``max_bytes``.
        max_bytes : int, default 256 MiB
            Bound on the working memory besides the returned table.
        max_table_bytes : int, optional
            Memory limit (bytes) for the tables and the working memory together
            (:func:`medseg.memory.potential_table_bytes`, estimated before anything is
            allocated); default: ``MEDSEG_MEMORY_LIMIT_GB`` if set, else half the physical
            memory. Above it, ``ResourceLimitError`` says how far to lower ``L`` or ``C``.

        Returns
        -------
        tables : (C, L, L, L) float32 array
            ``tables[c, a, b, d] = H_c(x_i = candidates[i, a], x_j = candidates[j, b],
            x_k = candidates[k, d])`` for ``(i, j, k) = cliques_[c]``; always finite,
            including for coincident candidates.
        """
        self._check_fitted()
        cand = np.ascontiguousarray(candidates, dtype=float)
        if cand.ndim != 3 or cand.shape[0] != self.n_landmarks_ or cand.shape[2] != 3:
            raise ParameterError(
                f"`candidates` must have shape ({self.n_landmarks_}, L, 3) (L candidates for "
                f"each of the {self.n_landmarks_} landmarks); got {cand.shape}"
            )
        if cand.shape[1] < 1 or not np.all(np.isfinite(cand)):
            raise ParameterError("`candidates` must hold at least one finite position per landmark")
        n_lab = cand.shape[1]
        n_cliques = len(self.cliques_)
        if chunk_size is None:
            chunk_size = potential_chunk_cliques(n_cliques, n_lab, chunk_bytes=max_bytes)
        chunk_size = int(max(1, min(chunk_size, n_cliques)))
        working = chunk_size * BYTES_PER_TRIPLE * n_lab**3
        check_memory(
            potential_table_bytes(n_cliques, n_lab, chunk_bytes=working),
            what=f"TripletPrior.potential_tables ({self.table_size(n_lab)}, and working memory)",
            hint=_table_hint(n_cliques, n_lab, working, max_table_bytes),
            limit=max_table_bytes,
        )
        out = np.empty((n_cliques, n_lab, n_lab, n_lab), dtype=np.float32)
        mixtures = self._mixtures()
        inv_fn = INVARIANTS[self.invariant]
        cand32 = cand.astype(np.float32)
        for start in range(0, n_cliques, chunk_size):
            sl = slice(start, min(start + chunk_size, n_cliques))
            cl = self.cliques_[sl]
            # float32 from here: the tables are float32, and it halves the time
            xi, xj, xk = (cand32[cl[:, q]] for q in range(3))  # (c, L, 3)
            d_ij = np.linalg.norm(xi[:, :, None] - xj[:, None], axis=-1)  # (c, a, b)
            d_jk = np.linalg.norm(xj[:, :, None] - xk[:, None], axis=-1)  # (c, b, d)
            d_ik = np.linalg.norm(xi[:, :, None] - xk[:, None], axis=-1)  # (c, a, d)
            inv = inv_fn(d_ij[:, :, :, None], d_jk[:, None, :, :], d_ik[:, :, None, :])
            logp = mixture_logpdf(inv.reshape(len(cl), -1, inv.shape[-1]), mixtures.subset(sl))
            out[sl] = (-self.alpha * logp).reshape(len(cl), n_lab, n_lab, n_lab)
        return out

    # ------------------------------------------------------------------ persistence
    def save(self, path) -> Path:
        """Write the fitted prior to one ``.npz`` file (:func:`medseg.io.save_arrays`).

        Returns
        -------
        Path
        """
        self._check_fitted()
        header, arrays = prior_state(self)
        return save_arrays(path, arrays, header=header)

    @classmethod
    def load(cls, path) -> TripletPrior:
        """Read a prior written by :meth:`save`; ``ModelFileError`` if the file is not one."""
        header, arrays = load_arrays(path, what="triplet prior")
        return prior_from_state(cls, header, arrays, source=str(path))
