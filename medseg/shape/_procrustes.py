"""Generalised Procrustes mean of landmark configurations (for clique selection only)."""

from __future__ import annotations

import numpy as np

from medseg._registration import similarity_fit

__all__ = ["procrustes_mean"]


def procrustes_mean(shapes: np.ndarray, *, n_iter: int = 20, tol: float = 1e-9) -> np.ndarray:
    """Mean shape after similarity alignment of every configuration to the running mean.

    Parameters
    ----------
    shapes : (S, N, 3) float array, mm

    Returns
    -------
    mean : (N, 3) float array, mm
        Centred at the origin, in the orientation of ``shapes[0]``, with the mean centroid
        size (root of the summed squared distances to the centroid) of the inputs.
    """
    centred = shapes - shapes.mean(axis=1, keepdims=True)
    sizes = np.sqrt((centred**2).sum(axis=(1, 2)))
    mean = centred[0].copy()
    for _ in range(n_iter):
        aligned = np.stack([similarity_fit(s, mean)(s) for s in centred])
        new = aligned.mean(axis=0)
        new -= new.mean(axis=0)
        norm = np.sqrt((new**2).sum())
        if norm == 0:
            break
        new *= sizes.mean() / norm
        new = similarity_fit(new, centred[0], allow_reflection=False).rotation @ new.T
        new = new.T
        if np.abs(new - mean).max() < tol * max(sizes.mean(), 1e-12):
            mean = new
            break
        mean = new
    return mean
