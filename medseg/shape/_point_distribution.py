"""The point distribution model of landmark configurations, and the mesh over the landmarks.

Training shapes are aligned by generalised Procrustes analysis (:mod:`medseg.geometry`:
similarity transforms, unit centroid size) and projected onto the tangent space of the mean;
PCA of the aligned shapes keeps the modes that explain a given share of the variance
(Cootes, Taylor, Cooper & Graham, 1995).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from medseg.errors import ParameterError
from medseg.geometry import generalised_procrustes, similarity_fit

__all__ = ["PointDistributionModel", "point_distribution_model", "landmark_mesh"]


def landmark_mesh(shape: np.ndarray) -> np.ndarray:
    """Triangles over landmarks: the hull of the landmarks projected onto a sphere.

    Parameters
    ----------
    shape : (N, 3) float array
        A landmark configuration (the mean shape), star-shaped about its centroid.

    Returns
    -------
    faces : (F, 3) int array
        Oriented so that face normals point away from the centroid.
    """
    centred = shape - shape.mean(0)
    unit = centred / np.maximum(np.linalg.norm(centred, axis=1, keepdims=True), 1e-12)
    faces = ConvexHull(unit).simplices.copy()
    a, b, c = (unit[faces[:, j]] for j in range(3))
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), a + b + c) < 0
    faces[flip] = faces[flip][:, ::-1]
    return faces


@dataclass(frozen=True)
class PointDistributionModel:
    """Result of :func:`point_distribution_model`.

    Attributes
    ----------
    mean : (N, 3) float array
        Mean shape: centred, unit centroid size, in the mean orientation of the inputs.
    modes : (K, N, 3) float array
        Orthonormal modes of variation (as flattened vectors).
    eigenvalues : (K,) float array
        Variance along each mode (unit-size frame), descending.
    mean_size : float
        Mean centroid size of the input shapes (their units, mm).
    aligned : (S, N, 3) float array
        Input shapes after Procrustes alignment and tangent projection.
    explained : float
        Fraction of the total variance the K modes explain.
    """

    mean: np.ndarray
    modes: np.ndarray
    eigenvalues: np.ndarray
    mean_size: float
    aligned: np.ndarray
    explained: float


def point_distribution_model(
    shapes: np.ndarray, *, variance: float = 0.98, max_iter: int = 50
) -> PointDistributionModel:
    """Generalised Procrustes alignment and PCA of landmark configurations.

    Parameters
    ----------
    shapes : (S, N, 3) float array, mm
        Landmark configurations in correspondence.
    variance : float, default 0.98
        Keep the fewest modes that explain at least this fraction of the variance.
    max_iter : int, default 50
        Procrustes iterations (the mean is re-estimated and re-aligned each time).

    Returns
    -------
    PointDistributionModel
        Invariant to a similarity transform of any input shape, except for the orientation
        of the mean, which is the mean (chordal L2) rotation of the inputs.
    """
    shapes = np.asarray(shapes, dtype=float)
    if shapes.ndim != 3 or shapes.shape[2] != 3 or len(shapes) < 2:
        raise ParameterError(f"`shapes` must be (S, N, 3) with S >= 2, got {shapes.shape}")
    gpa = generalised_procrustes(shapes, max_iter=max_iter)
    centred = shapes - shapes.mean(axis=1, keepdims=True)
    unit = centred / gpa.sizes[:, None, None]
    # Unit pose = the mean orientation of the inputs: rotate the mean (and the aligned
    # shapes with it) into it.
    rotations = Rotation.from_matrix(np.stack([similarity_fit(gpa.mean, x).rotation for x in unit]))
    turn = rotations.mean().as_matrix()
    mean = gpa.mean @ turn.T
    aligned = gpa.aligned @ turn.T
    aligned = aligned / np.einsum("snd,nd->s", aligned, mean)[:, None, None]  # tangent space
    dev = (aligned - mean).reshape(len(aligned), -1)
    _, sv, vt = np.linalg.svd(dev, full_matrices=False)
    eig = sv**2 / (len(aligned) - 1)
    total = eig.sum()
    if total > 0:
        ratio = np.cumsum(eig) / total
        k = min(int(np.searchsorted(ratio, variance - 1e-12) + 1), len(eig))
        explained = float(ratio[k - 1])
    else:
        k, explained = 0, 1.0
    return PointDistributionModel(
        mean=mean,
        modes=vt[:k].reshape(k, -1, 3),
        eigenvalues=eig[:k],
        mean_size=float(gpa.sizes.mean()),
        aligned=aligned,
        explained=explained,
    )
