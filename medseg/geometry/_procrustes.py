"""Generalised Procrustes analysis of landmark configurations, without reflection.

One alignment serves the clique selection and the prior's mean shape
(:func:`procrustes_mean`), the point distribution model of the active shape search, and the
choice of the template case (:func:`procrustes_disparity`). Reflections are never allowed:
a mirrored configuration is a different shape (the handedness term depends on it).

References
----------
.. [1] J. C. Gower, "Generalized Procrustes analysis", Psychometrika 40(1), 1975.
   :doi:`10.1007/BF02291478`
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from medseg.errors import ParameterError
from medseg.geometry._similarity import similarity_fit

__all__ = [
    "ProcrustesAlignment",
    "generalised_procrustes",
    "procrustes_mean",
    "procrustes_disparity",
]


@dataclass(frozen=True)
class ProcrustesAlignment:
    """Result of :func:`generalised_procrustes`.

    Attributes
    ----------
    mean : (N, 3) float array
        Mean configuration: centred, unit centroid size, in the orientation of the first
        input shape.
    aligned : (S, N, 3) float array
        Every input, centred and scaled to unit size, then moved onto ``mean`` by its
        least-squares similarity (proper rotation).
    sizes : (S,) float array
        Centroid size of each input (root of the summed squared distances to its centroid),
        in the inputs' units.
    """

    mean: np.ndarray
    aligned: np.ndarray
    sizes: np.ndarray


def _unit_shapes(shapes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    shapes = np.asarray(shapes, dtype=float)
    if shapes.ndim != 3 or shapes.shape[2] != 3 or len(shapes) < 1:
        raise ParameterError(f"`shapes` must be an (S, N, 3) array with S >= 1, got {shapes.shape}")
    centred = shapes - shapes.mean(axis=1, keepdims=True)
    sizes = np.sqrt((centred**2).sum(axis=(1, 2)))
    if not np.all(sizes > 0):
        raise ParameterError("every shape of `shapes` needs landmarks at two or more positions")
    return centred / sizes[:, None, None], sizes


def _align(unit: np.ndarray, mean: np.ndarray) -> np.ndarray:
    return np.stack([similarity_fit(x, mean)(x) for x in unit])


def generalised_procrustes(
    shapes: np.ndarray, *, max_iter: int = 50, tol: float = 1e-10
) -> ProcrustesAlignment:
    """Align configurations to their common mean by similarity transforms (no reflection).

    Parameters
    ----------
    shapes : (S, N, 3) float array
        Landmark configurations in correspondence (mm).
    max_iter : int, default 50
        Re-estimations of the mean.
    tol : float, default 1e-10
        Stop when no coordinate of the unit-size mean moves more than this.

    Returns
    -------
    ProcrustesAlignment
        Invariant to a similarity transform of any input except the first, which fixes the
        orientation of the mean.
    """
    unit, sizes = _unit_shapes(shapes)
    mean = unit[0].copy()
    for _ in range(max_iter):
        new = _align(unit, mean).mean(axis=0)
        new -= new.mean(axis=0)
        new /= np.linalg.norm(new)
        new = new @ similarity_fit(new, mean).rotation.T  # keep the mean's orientation
        converged = np.abs(new - mean).max() < tol
        mean = new
        if converged:
            break
    mean = mean @ similarity_fit(mean, unit[0]).rotation.T  # the first shape's orientation
    return ProcrustesAlignment(mean=mean, aligned=_align(unit, mean), sizes=sizes)


def procrustes_mean(shapes: np.ndarray, *, max_iter: int = 50) -> np.ndarray:
    """Procrustes mean shape in the inputs' units.

    Parameters
    ----------
    shapes : (S, N, 3) float array, mm

    Returns
    -------
    mean : (N, 3) float array, mm
        Centred at the origin, in the orientation of ``shapes[0]``, with the mean centroid
        size of the inputs.
    """
    gpa = generalised_procrustes(shapes, max_iter=max_iter)
    return gpa.mean * gpa.sizes.mean()


def procrustes_disparity(a: np.ndarray, b: np.ndarray) -> float:
    """Squared residual of the best similarity (no reflection) between two configurations.

    Both are centred and scaled to unit centroid size first, so the value lies in [0, 1]
    and is symmetric in ``a`` and ``b``.

    Parameters
    ----------
    a, b : (N, 3) float arrays
    """
    unit, _ = _unit_shapes(np.stack([a, b]))
    moved = similarity_fit(unit[0], unit[1])(unit[0])
    return float(((moved - unit[1]) ** 2).sum())
