"""Training samples for the landmark forests: positives near each landmark, balanced negatives.

Positives are the voxels within ``positive_radius_mm`` of a landmark. Negatives come in three
equal parts: a ring just outside the positive ball (sharp localisation), voxels near the *other*
landmarks (hard negatives: similar-looking boundary points) and voxels anywhere in the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from medseg.io import physical_to_voxel, voxel_to_physical

__all__ = ["LandmarkSamples", "sample_landmark_voxels"]


@dataclass
class LandmarkSamples:
    """Voxel samples of one image, for every landmark.

    Attributes
    ----------
    positives : list of (P_i,) int arrays
        Flat voxel indices (into the ``(Z, Y, X)`` array) within the positive radius of
        landmark ``i``; empty when the landmark is missing or outside the image.
    negatives : list of (Q_i,) int arrays
        Flat voxel indices of negatives for landmark ``i``.
    positive_distances : list of (P_i,) float arrays, mm
        Distance of each positive voxel centre to its landmark.
    """

    positives: list[np.ndarray]
    negatives: list[np.ndarray]
    positive_distances: list[np.ndarray]


def _ball(image: sitk.Image, centre_mm: np.ndarray, radius_mm: float, shape) -> tuple:
    """Flat indices and distances (mm) of the voxels whose centres lie within a ball."""
    spacing = np.asarray(image.GetSpacing(), dtype=float)[::-1]
    centre = physical_to_voxel(image, centre_mm)
    half = np.ceil(radius_mm / spacing).astype(int) + 1
    lo = np.maximum(np.floor(centre).astype(int) - half, 0)
    hi = np.minimum(np.ceil(centre).astype(int) + half + 1, shape)
    if np.any(hi <= lo):
        return np.empty(0, dtype=np.int64), np.empty(0)
    grid = np.stack(
        np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi, strict=True)], indexing="ij"), axis=-1
    ).reshape(-1, 3)
    dist = np.linalg.norm(voxel_to_physical(image, grid) - centre_mm, axis=1)
    keep = dist <= radius_mm
    return np.ravel_multi_index(grid[keep].T, shape), dist[keep]


def _inside(image: sitk.Image, point_mm: np.ndarray, shape) -> bool:
    zyx = physical_to_voxel(image, point_mm)
    return bool(np.all(zyx >= -0.5) and np.all(zyx <= np.asarray(shape) - 0.5))


def sample_landmark_voxels(
    image: sitk.Image,
    landmarks: np.ndarray,
    *,
    positive_radius_mm: float,
    n_negative: int,
    max_positive: int,
    random_state: np.random.RandomState,
) -> LandmarkSamples:
    """Positive and negative voxels of one image for every landmark.

    Parameters
    ----------
    image : 3D SimpleITK image
        Supplies the geometry.
    landmarks : (N, 3) float array, mm, (x, y, z)
        Rows with a NaN are missing landmarks: they get no samples.
    positive_radius_mm : float, mm
        Voxels within this distance of a landmark are its positives; the nearest voxel always
        is, so a radius below the spacing still gives one positive.
    n_negative : int
        Negatives per landmark: a third in the ring ``(r, 4 r]`` around the landmark, a third
        within ``4 r`` of the other landmarks, the rest uniform over the image.
    max_positive : int
        At most this many positives per landmark (a random subset, the nearest voxel kept).
    random_state : numpy RandomState

    Returns
    -------
    LandmarkSamples
    """
    shape = tuple(int(s) for s in image.GetSize()[::-1])
    n_vox = int(np.prod(shape))
    rng = random_state
    spacing = np.asarray(image.GetSpacing(), dtype=float)
    r_pos = float(positive_radius_mm)
    r_ring = 4.0 * max(r_pos, float(spacing.max()))
    n_lm = len(landmarks)
    valid = [bool(np.isfinite(p).all()) and _inside(image, p, shape) for p in landmarks]

    # Neighbourhood (ring radius) of every landmark, shared by its own ring and the others'.
    hoods = []
    for i in range(n_lm):
        if valid[i]:
            hoods.append(_ball(image, landmarks[i], r_ring, shape))
        else:
            hoods.append((np.empty(0, dtype=np.int64), np.empty(0)))

    # How many neighbourhoods hold each voxel: the union of the others' is where it is > own.
    cover = np.bincount(np.concatenate([flat for flat, _ in hoods]), minlength=n_vox)
    covered = cover > 0
    positives, negatives, pos_dist = [], [], []
    n_ring = n_negative // 3
    n_other = n_negative // 3
    n_uniform = n_negative - n_ring - n_other
    for i in range(n_lm):
        if not valid[i]:
            positives.append(np.empty(0, dtype=np.int64))
            negatives.append(np.empty(0, dtype=np.int64))
            pos_dist.append(np.empty(0))
            continue
        flat, dist = hoods[i]
        within = dist <= r_pos
        is_pos = within.copy()
        is_pos[np.argmin(dist)] = True
        pos, pdist = flat[is_pos], dist[is_pos]
        if pos.size > max_positive:
            nearest = np.argmin(pdist)
            rest = np.delete(np.arange(pos.size), nearest)
            keep = np.concatenate([[nearest], rng.choice(rest, max_positive - 1, replace=False)])
            pos, pdist = pos[keep], pdist[keep]
        positives.append(pos)
        pos_dist.append(pdist)
        pos_set = set(pos.tolist())

        ring = flat[~is_pos]
        ring = rng.choice(ring, min(n_ring, ring.size), replace=False) if ring.size else ring

        # In another landmark's neighbourhood and farther than r_pos from this one: every
        # voxel outside its own ball is (the ball's radius is at least r_pos), so only its
        # own ball's voxels need their distance, and they have it already.
        in_pool = covered.copy()
        in_pool[flat[(cover[flat] == 1) | within]] = False
        pool = np.flatnonzero(in_pool)
        other = rng.choice(pool, min(n_other, pool.size), replace=False) if pool.size else pool

        n_u = n_uniform + (n_ring - ring.size) + (n_other - other.size)
        uni = rng.randint(0, n_vox, size=2 * n_u + 8)
        uni_zyx = np.stack(np.unravel_index(uni, shape), axis=-1)
        far = np.linalg.norm(voxel_to_physical(image, uni_zyx) - landmarks[i], axis=1) > r_pos
        uni = uni[far][:n_u]
        neg = np.concatenate([ring, other, uni]).astype(np.int64)
        if pos_set:
            neg = neg[~np.isin(neg, pos)]
        negatives.append(neg)
    return LandmarkSamples(positives, negatives, pos_dist)
