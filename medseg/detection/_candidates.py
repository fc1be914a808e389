"""Candidate positions of the landmarks: the ``CandidateSet`` and how a detector finds it.

A fitted detector scores the voxels of a stride grid, non-maximum suppression in mm keeps the
best spatially distinct ones of each landmark, and refinement moves each to the best voxel of
its full-resolution neighbourhood and to a sub-voxel peak. The scoring itself (features,
cascade, forests) is :mod:`medseg.detection._prediction`; this module turns scores into
candidates.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk
from numpy.typing import ArrayLike
from scipy import ndimage
from scipy.spatial import cKDTree

from medseg.detection._prediction import (
    check_mask,
    forest_features,
    predict_cascade,
    predict_rows,
    scored_region,
    stride_grid,
)
from medseg.errors import ParameterError
from medseg.io import physical_to_voxel, voxel_to_physical

__all__ = ["CandidateSet", "detect_candidates", "non_maximum_suppression", "subvoxel_peak"]


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

    def mapped(self, transform: Callable[[np.ndarray], np.ndarray], image) -> CandidateSet:
        """The same candidates moved by a point ``transform`` (mm -> mm) into ``image``.

        Positions are mapped, voxel indices recomputed in ``image``; probabilities stay.
        How candidates found in one frame (the shape's, or an unperturbed image) are used
        in another.
        """
        positions = np.asarray(transform(self.positions.reshape(-1, 3)), dtype=float)
        positions = positions.reshape(self.positions.shape)
        voxels = physical_to_voxel(image, positions.reshape(-1, 3)).reshape(positions.shape)
        return CandidateSet(
            positions=positions,
            probabilities=self.probabilities,
            voxels=voxels,
            floor=self.floor,
            meta=dict(self.meta),
        )

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
            raise ParameterError(f"`eps` must be in (0, 1), got {eps}")
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
            raise ParameterError(
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


# ------------------------------------------------------------------- a detector's candidates
def detect_candidates(
    detector,
    image: sitk.Image,
    *,
    n_candidates: int,
    min_distance_mm: float | None,
    mask,
    stride: int,
    refine: bool,
    floor: float,
    precomputed: np.ndarray | None,
    screen: tuple[int, int] | None = None,
) -> CandidateSet:
    """:meth:`LandmarkDetector.candidates` of a fitted detector (the arguments are its own)."""
    n_candidates = int(n_candidates)
    if n_candidates < 1:
        raise ParameterError(f"`n_candidates` must be >= 1, got {n_candidates}")
    if not 0 < floor < 1:
        raise ParameterError(f"`floor` must be in (0, 1), got {floor}")
    screen = _check_screen(screen, n_candidates)
    timings = {}
    t0 = time.perf_counter()
    feats = forest_features(detector, image, precomputed)
    timings["features_s"] = time.perf_counter() - t0
    shape = feats.shape[:3]
    flat = feats.reshape(-1, feats.shape[-1])
    mask_arr = check_mask(image, mask, shape)
    spacing = np.asarray(image.GetSpacing(), dtype=float)[::-1]
    if min_distance_mm is None:
        min_distance_mm = max(float(detector.positive_radius_mm), 2.0 * float(spacing.max()))
    stride = int(stride)
    region = scored_region(shape, mask_arr, stride)
    coarse_on_grid = region[::stride, ::stride, ::stride]
    on_grid = coarse_on_grid.sum() == region.sum()
    t0 = time.perf_counter()
    if on_grid:
        grid_shape, grid_zyx, grid_rows = stride_grid(shape, stride)
        scored = coarse_on_grid.ravel()
        footprint = float(min_distance_mm) / (spacing * stride)
    else:  # thin mask scored voxel by voxel
        grid_shape = None
        grid_zyx = np.argwhere(region)
        grid_rows = np.ravel_multi_index(grid_zyx.T, shape)
        scored = np.ones(len(grid_rows), dtype=bool)
        footprint = None
    proba = np.full((len(grid_rows), detector.n_landmarks_), -np.inf, dtype=np.float64)
    proba[scored] = predict_cascade(
        detector, flat[grid_rows[scored]], rejected=-np.inf, screen=screen
    )
    timings["predict_s"] = time.perf_counter() - t0
    points_mm = voxel_to_physical(image, grid_zyx)

    t0 = time.perf_counter()
    n_lm = detector.n_landmarks_
    n_keep = min(n_candidates, int(scored.sum()))
    vox = np.zeros((n_lm, n_candidates, 3))
    prob = np.full((n_lm, n_candidates), floor)
    for i in range(n_lm):
        keep = non_maximum_suppression(
            proba[:, i],
            points_mm,
            n=n_keep,
            min_distance_mm=float(min_distance_mm),
            grid_shape=grid_shape,
            footprint_vox=footprint,
        )
        vox[i, : len(keep)] = grid_zyx[keep]
        prob[i, : len(keep)] = proba[keep, i]
        if len(keep) < n_candidates:  # fewer scored voxels than candidates: repeat the last
            vox[i, len(keep) :] = vox[i, len(keep) - 1]
            prob[i, len(keep) :] = floor
    timings["nms_s"] = time.perf_counter() - t0
    if refine:
        t0 = time.perf_counter()
        vox, prob = _refine(detector, flat, shape, mask_arr, vox, prob, max(stride, 1))
        timings["refine_s"] = time.perf_counter() - t0
    positions = voxel_to_physical(image, vox.reshape(-1, 3)).reshape(vox.shape)
    return CandidateSet(
        positions=positions,
        probabilities=np.clip(prob, floor, 1.0),
        voxels=vox,
        floor=float(floor),
        meta={
            "stride": stride,
            "min_distance_mm": float(min_distance_mm),
            "refine": bool(refine),
            "mode": detector.mode,
            "screen": screen,
            "timings": timings,
        },
    )


def _check_screen(screen, n_candidates: int) -> tuple[int, int] | None:
    """``screen`` as ``(trees, rows)`` of ints (or None); ParameterError if it cannot hold
    ``n_candidates`` candidates."""
    if screen is None:
        return None
    try:
        trees, rows = (int(v) for v in screen)
    except (TypeError, ValueError):
        raise ParameterError(f"`screen` must be (trees, rows) or None, got {screen!r}") from None
    if trees < 1 or rows < n_candidates:
        raise ParameterError(
            f"`screen` = (trees, rows) needs trees >= 1 and rows >= n_candidates "
            f"({n_candidates}), got {screen!r}"
        )
    return trees, rows


def _refine(detector, flat, shape, mask, vox, prob, half):
    """Best voxel and sub-voxel peak of each candidate's full-resolution neighbourhood."""
    n_lm, n_c, _ = vox.shape
    offsets = np.stack(np.meshgrid(*[np.arange(-half, half + 1)] * 3, indexing="ij"), -1).reshape(
        -1, 3
    )
    side = 2 * half + 1
    centres = np.rint(vox).astype(int)
    cubes = centres[:, :, None, :] + offsets[None, None]  # (N, L, K, 3)
    valid = np.all((cubes >= 0) & (cubes < np.asarray(shape)), axis=-1)
    clipped = np.clip(cubes, 0, np.asarray(shape) - 1)
    if mask is not None:
        valid &= mask[tuple(np.moveaxis(clipped, -1, 0))]
    rows = np.ravel_multi_index(tuple(np.moveaxis(clipped, -1, 0)), shape)
    values = np.full(valid.shape, np.nan)
    if detector.mode == "per_landmark":
        for i in range(n_lm):
            sel = valid[i]
            # neighbourhoods of one landmark's candidates overlap: score each voxel once
            unique, inverse = np.unique(rows[i][sel], return_inverse=True)
            values[i][sel] = predict_rows(detector, flat[unique], [i])[inverse, 0]
    else:  # one pass of the multi-class forest over every neighbourhood
        unique, inverse = np.unique(rows[valid], return_inverse=True)
        proba = predict_rows(detector, flat[unique])
        lm_index = np.broadcast_to(np.arange(n_lm)[:, None, None], valid.shape)[valid]
        values[valid] = proba[inverse, lm_index]
    new_vox, new_prob = vox.copy(), prob.copy()
    for i in range(n_lm):
        for c in range(n_c):
            v = values[i, c]
            if np.all(np.isnan(v)):
                continue
            best = int(np.nanargmax(v))
            centre = v.size // 2
            if np.isfinite(v[centre]) and v[best] <= v[centre]:
                best = centre  # ties (flat maps) keep the candidate where it is
            cube = v.reshape(side, side, side)
            local = np.unravel_index(best, cube.shape)
            offset = subvoxel_peak(cube, local)
            new_vox[i, c] = cubes[i, c, best] + offset
            new_prob[i, c] = max(v[best], 0.0)
    order = np.argsort(-new_prob, axis=1, kind="stable")
    new_vox = np.take_along_axis(new_vox, order[..., None], axis=1)
    new_prob = np.take_along_axis(new_prob, order, axis=1)
    return new_vox, new_prob
