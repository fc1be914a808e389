"""The one similarity fit: rotation (proper unless asked), uniform scale and translation.

Every alignment of point sets in medseg (Procrustes, ICP, the active-shape search, the
shape's own frame) goes through :func:`similarity_fit`.

References
----------
.. [1] S. Umeyama, "Least-squares estimation of transformation parameters between two point
   patterns", IEEE TPAMI 13(4), 1991. :doi:`10.1109/34.88573`
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Similarity", "similarity_fit"]


@dataclass(frozen=True)
class Similarity:
    """``y = scale * x @ rotation.T + translation``; ``rotation`` may be improper (det -1)."""

    rotation: np.ndarray  # (3, 3)
    scale: float
    translation: np.ndarray  # (3,)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(points, float) @ self.rotation.T + self.translation

    def inverse(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, float) - self.translation) @ self.rotation / self.scale

    def compose(self, first: Similarity) -> Similarity:
        """The transform ``self(first(x))``."""
        return Similarity(
            rotation=self.rotation @ first.rotation,
            scale=self.scale * first.scale,
            translation=self.scale * first.translation @ self.rotation.T + self.translation,
        )

    def matrix(self) -> np.ndarray:
        """Homogeneous (4, 4) matrix acting on column vectors (x, y, z, 1)."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m


def similarity_fit(
    src: np.ndarray,
    dst: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    allow_reflection: bool = False,
) -> Similarity:
    """Least-squares similarity mapping paired ``src`` points onto ``dst`` (Umeyama).

    Parameters
    ----------
    src, dst : (N, 3) float arrays, mm
    weights : (N,) float array, optional
    allow_reflection : bool
        If False the rotation is proper (det +1).
    """
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    xs = src - mu_s
    xd = dst - mu_d
    cov = (xd * w[:, None]).T @ xs
    u, sig, vt = np.linalg.svd(cov)
    d = np.ones(3)
    if not allow_reflection and np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[-1] = -1.0
    rot = (u * d) @ vt
    var_s = float(w @ np.einsum("ij,ij->i", xs, xs))
    scale = float((sig * d).sum() / var_s) if var_s > 0 else 1.0
    return Similarity(rotation=rot, scale=scale, translation=mu_d - scale * mu_s @ rot.T)
