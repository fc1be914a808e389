"""Candidate positions from probability maps: non-maximum suppression in mm, sub-voxel peaks."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage
from scipy.spatial import cKDTree

from medseg.errors import MedsegError

__all__ = ["CandidateSet", "non_maximum_suppression", "subvoxel_peak"]


@dataclass
class CandidateSet:
    """The L best, spatially distinct positions of each of N landmarks.

    Attributes
    ----------
    positions : (N, L, 3) float array, mm, (x, y, z)
        Candidate positions in the image's physical frame, best first.
    probabilities : (N, L) float array
        Detector probability of each candidate, in ``[floor, 1]``: never 0, so the unaries
        stay finite.
    voxels : (N, L, 3) float array
        Continuous ``(z, y, x)`` indices of the candidates in the image array.
    floor : float
        The probability floor applied.
    meta : dict
        How the candidates were found (stride, min_distance_mm, ...).
    """

    positions: np.ndarray
    probabilities: np.ndarray
    voxels: np.ndarray
    floor: float = 1e-6
    meta: dict = field(default_factory=dict)

    @property
    def n_landmarks(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_candidates(self) -> int:
        return int(self.positions.shape[1])

    def unaries(self, *, eps: float | None = None) -> np.ndarray:
        """Singleton potentials ``U_i(x_i) = -log p(I | x_i)`` of the MRF.

        Parameters
        ----------
        eps : float, optional
            Probability floor (default: the set's ``floor``), so the potentials are finite.

        Returns
        -------
        unaries : (N, L) float array, >= 0
        """
        eps = self.floor if eps is None else float(eps)
        if not 0 < eps < 1:
            raise MedsegError(f"`eps` must be in (0, 1), got {eps}")
        return -np.log(np.clip(self.probabilities, eps, 1.0))

    def distances(self, landmarks: ArrayLike) -> np.ndarray:
        """Distance of every candidate to the reference landmark.

        Parameters
        ----------
        landmarks : (N, 3) float array, mm, (x, y, z)
            NaN rows (missing landmarks) give NaN distances.

        Returns
        -------
        distances : (N, L) float array, mm
        """
        ref = np.asarray(landmarks, dtype=float)
        if ref.shape != (self.n_landmarks, 3):
            raise MedsegError(
                f"`landmarks` has shape {ref.shape}; expected ({self.n_landmarks}, 3) in mm"
            )
        return np.linalg.norm(self.positions - ref[:, None, :], axis=-1)

    def recall(self, landmarks: ArrayLike, *, radius_mm: float, n: int | None = None) -> np.ndarray:
        """Whether each landmark has one of its first ``n`` candidates within ``radius_mm``.

        Returns
        -------
        hit : (N,) float array of 0/1, NaN for missing reference landmarks
        """
        d = self.distances(landmarks)[:, : (n or self.n_candidates)]
        hit = (d <= radius_mm).any(axis=1).astype(float)
        hit[np.isnan(d).all(axis=1)] = np.nan
        return hit


def _ellipsoid_footprint(radius_vox: np.ndarray) -> np.ndarray:
    half = np.floor(radius_vox).astype(int)
    axes = [np.arange(-h, h + 1) / max(r, 1e-9) for h, r in zip(half, radius_vox, strict=True)]
    zz, yy, xx = np.meshgrid(*axes, indexing="ij")
    return (zz**2 + yy**2 + xx**2) <= 1.0 + 1e-9


def non_maximum_suppression(
    scores: np.ndarray,
    points_mm: np.ndarray,
    *,
    n: int,
    min_distance_mm: float,
    grid_shape: tuple[int, ...] | None = None,
    footprint_vox: ArrayLike | None = None,
    max_peaks: int | None = None,
) -> np.ndarray:
    """Greedy non-maximum suppression with a minimum physical distance.

    Parameters
    ----------
    scores : (M,) float array
        Score of each scored point (higher is better).
    points_mm : (M, 3) float array, mm
        Physical position of each point.
    n : int
        How many points to keep.
    min_distance_mm : float, mm
        Kept points are at least this far apart (strictly more than).
    grid_shape : tuple, optional
        When the points are a full ``(Z, Y, X)`` grid in C order, a maximum filter with the
        ellipsoidal footprint ``footprint_vox`` (radii in grid steps per axis) first keeps only
        local maxima, which makes the greedy pass short.
    footprint_vox : (3,) float array, optional
    max_peaks : int, optional
        At most this many of the best local maxima enter the greedy pass (default ``50 n``).

    Returns
    -------
    keep : (K,) int array
        Indices into ``scores`` of the kept points, best first; ``K < n`` only when fewer than
        ``n`` points exist. When the local maxima are too few (e.g. a flat map), the rest is
        filled with the best remaining points that keep the minimum distance, then with any.
    """
    scores = np.asarray(scores, dtype=float)
    m = scores.size
    if m == 0:
        return np.empty(0, dtype=np.int64)
    max_peaks = 50 * n if max_peaks is None else max_peaks
    candidates = np.arange(m)
    if grid_shape is not None and footprint_vox is not None:
        grid = scores.reshape(grid_shape)
        fp = _ellipsoid_footprint(np.asarray(footprint_vox, dtype=float))
        local_max = grid == ndimage.maximum_filter(
            grid, footprint=fp, mode="constant", cval=-np.inf
        )
        candidates = np.flatnonzero(local_max.ravel() & np.isfinite(scores))
    if candidates.size > max_peaks:
        top = np.argpartition(-scores[candidates], max_peaks - 1)[:max_peaks]
        candidates = candidates[top]
    order = candidates[np.argsort(-scores[candidates], kind="stable")]
    keep = _greedy(order, points_mm, n, min_distance_mm)
    if len(keep) < n:  # flat or tiny maps: widen the pool to every point
        finite = np.flatnonzero(np.isfinite(scores))
        pool = finite[np.argsort(-scores[finite], kind="stable")][: max(max_peaks, 50 * n)]
        pool = pool[~np.isin(pool, keep)]
        keep = _greedy(np.concatenate([keep, pool]).astype(np.int64), points_mm, n, min_distance_mm)
        if len(keep) < n:
            rest = finite[~np.isin(finite, keep)]
            rest = rest[np.argsort(-scores[rest], kind="stable")][: n - len(keep)]
            keep = np.concatenate([keep, rest]).astype(np.int64)
    return np.asarray(keep, dtype=np.int64)


def _greedy(order: np.ndarray, points_mm: np.ndarray, n: int, min_distance_mm: float) -> np.ndarray:
    pts = points_mm[order]
    tree = cKDTree(pts)
    suppressed = np.zeros(order.size, dtype=bool)
    keep = []
    for k in range(order.size):
        if suppressed[k]:
            continue
        keep.append(order[k])
        if len(keep) == n:
            break
        if min_distance_mm > 0:
            suppressed[tree.query_ball_point(pts[k], min_distance_mm)] = True
    return np.asarray(keep, dtype=np.int64)


def subvoxel_peak(values: np.ndarray, centre: tuple[int, int, int]) -> np.ndarray:
    """Offset of a peak by a 1D parabola through the neighbours along each axis.

    Parameters
    ----------
    values : (Z, Y, X) float array
        A map that holds the peak; NaN for unscored voxels.
    centre : (3,) int
        Index of the peak voxel.

    Returns
    -------
    offset : (3,) float array, voxels, each in [-0.5, 0.5]
        Zero along an axis where a neighbour is missing or the parabola is not concave.
    """
    offset = np.zeros(3)
    c = np.asarray(centre)
    f0 = values[tuple(c)]
    for ax in range(3):
        lo, hi = c.copy(), c.copy()
        lo[ax] -= 1
        hi[ax] += 1
        if lo[ax] < 0 or hi[ax] >= values.shape[ax]:
            continue
        fm, fp = values[tuple(lo)], values[tuple(hi)]
        denom = fm - 2.0 * f0 + fp
        if np.isfinite(denom) and denom < 0:
            offset[ax] = np.clip(0.5 * (fm - fp) / denom, -0.5, 0.5)
    return offset
