"""A reflection-sensitive triplet term: on which side of each triangle the boundary faces.

The triplet invariants of :class:`TripletPrior` (relative distances, angles, size) are blind
to reflection, and so are rotation-invariant image features: for a nearly mirror-symmetric
structure the labelling that swaps every landmark with its mirror partner looks as good as
the right one to both. What tells them apart is handedness. For a clique ``(i, j, k)`` with
boundary directions ``g`` at its corners (the image gradient, see
:func:`medseg.detection.gradient_directions`), the cosine between the triangle's normal
``(x_j - x_i) x (x_k - x_i)`` and ``g_i + g_j + g_k`` is unchanged by rotation, translation and
scaling of the image, and changes sign under a reflection. Its sign is learned per clique from
the training shapes, with how consistently it holds, and a configuration that faces the other
way pays the log-odds of that consistency. The idea is the orientation (Gaussian map) term of
Zeng et al. (CVPR 2010) for surface matching, carried over to landmarks in an image.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from sklearn.base import BaseEstimator

from medseg.errors import ModelFileError, NotFittedError, ParameterError
from medseg.io import check_format, load_arrays, save_arrays

__all__ = ["OrientationPrior", "triangle_orientation"]


def triangle_orientation(xi, xj, xk, gi, gj, gk) -> np.ndarray:
    """Cosine between a triangle's normal and the summed directions at its corners.

    Parameters
    ----------
    xi, xj, xk : (..., 3) float arrays, mm
        Corners (broadcast against each other).
    gi, gj, gk : (..., 3) float arrays
        Directions at the corners (unit vectors, or zero where unknown).

    Returns
    -------
    (...) float array in [-1, 1]
        0 for a degenerate triangle or vanishing directions.
    """
    normal = np.cross(np.subtract(xj, xi), np.subtract(xk, xi))
    direction = np.add(np.add(gi, gj), gk)
    dot = np.einsum("...d,...d->...", normal, direction)
    scale = np.linalg.norm(normal, axis=-1) * np.linalg.norm(direction, axis=-1)
    return np.divide(dot, scale, out=np.zeros_like(dot, dtype=float), where=scale > 1e-12)


def _orientation_grid(xi, xj, xk, gi, gj, gk) -> np.ndarray:
    """:func:`triangle_orientation` of every triple of three candidate lists, per clique.

    ``xi, xj, xk, gi, gj, gk``: (c, L, 3). Returns (c, L, L, L) with ``[:, a, b, d]`` the
    triangle ``(xi[a], xj[b], xk[d])``. The edges and the pairwise sums are formed on
    ``L x L`` grids and only the products that need all three corners on ``L x L x L``, one
    coordinate at a time: twice as fast as broadcasting the vector operations.
    """
    e1 = xj[:, None, :, :] - xi[:, :, None, :]  # (c, a, b, 3)
    e2 = xk[:, None, :, :] - xi[:, :, None, :]  # (c, a, d, 3)
    g_ab = gi[:, :, None, :] + gj[:, None, :, :]
    shape = (len(xi), xi.shape[1], xj.shape[1], xk.shape[1])
    dot, nn, gg = np.zeros(shape), np.zeros(shape), np.zeros(shape)
    for p, q, r in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        normal = e1[:, :, :, None, q] * e2[:, :, None, :, r]
        normal -= e1[:, :, :, None, r] * e2[:, :, None, :, q]
        direction = g_ab[:, :, :, None, p] + gk[:, None, None, :, p]
        dot += normal * direction
        nn += normal * normal
        gg += direction * direction
    scale = np.sqrt(nn * gg)
    return np.divide(dot, scale, out=np.zeros(shape), where=scale > 1e-12)


def _cost(cos, reference, penalty):
    """``(1 - r cos) / 2`` of the penalty: 0 facing the learned way, all of it facing away."""
    return 0.5 * (1.0 - reference * cos) * penalty


class OrientationPrior(BaseEstimator):
    """Per-clique handedness of the landmark triangles against the boundary directions.

    Parameters
    ----------
    pseudo_count : float, default 1.0
        Laplace smoothing of the agreement frequency, so that a handedness seen in every
        training shape still costs a finite amount to break.

    Attributes
    ----------
    cliques_ : (C, 3) int array
    reference_ : (C,) float array of +1 / -1
        The handedness most training shapes have.
    agreement_ : (C,) float array in (0.5, 1)
        Smoothed fraction of training shapes with that handedness.
    n_training_shapes_ : int
    """

    def __init__(self, *, pseudo_count: float = 1.0):
        self.pseudo_count = pseudo_count

    def fit(
        self, shapes: ArrayLike, directions: ArrayLike, *, cliques: ArrayLike
    ) -> OrientationPrior:
        """Learn the handedness of every clique.

        Parameters
        ----------
        shapes : (S, N, 3) float array, mm
            Training landmarks in correspondence, each in its own pose.
        directions : (S, N, 3) float array
            Boundary directions at those landmarks in the same images.
        cliques : (C, 3) int array
            The prior's cliques.
        """
        shapes = np.asarray(shapes, dtype=float)
        directions = np.asarray(directions, dtype=float)
        cliques = np.asarray(cliques, dtype=np.int64)
        if shapes.ndim != 3 or shapes.shape[-1] != 3 or directions.shape != shapes.shape:
            raise ParameterError(
                f"`shapes` and `directions` must both have shape (S, N, 3); got {shapes.shape} "
                f"and {directions.shape}"
            )
        if (
            cliques.ndim != 2
            or cliques.shape[1] != 3
            or cliques.min(initial=0) < 0
            or (cliques.max(initial=0) >= shapes.shape[1])
        ):
            raise ParameterError(f"`cliques` must be (C, 3) indices below {shapes.shape[1]}")
        if not float(self.pseudo_count) > 0:
            raise ParameterError(f"`pseudo_count` must be > 0, got {self.pseudo_count}")
        i, j, k = cliques.T
        cos = triangle_orientation(
            shapes[:, i], shapes[:, j], shapes[:, k],
            directions[:, i], directions[:, j], directions[:, k],
        )  # fmt: skip
        signs = np.sign(cos)  # (S, C)
        self.reference_ = np.where(signs.sum(axis=0) >= 0, 1.0, -1.0)
        agree = (signs == self.reference_).sum(axis=0)
        a = float(self.pseudo_count)
        self.agreement_ = (agree + a) / (len(shapes) + 2 * a)
        self.cliques_ = cliques
        self.n_training_shapes_ = int(len(shapes))
        return self

    def _check_fitted(self) -> None:
        if not hasattr(self, "reference_"):
            raise NotFittedError("this OrientationPrior is not fitted yet: call fit(...)")

    @property
    def penalty_(self) -> np.ndarray:
        """(C,) cost of the opposite handedness: the log-odds of the clique's agreement."""
        self._check_fitted()
        p = np.clip(self.agreement_, 0.5, 1.0 - 1e-9)
        return np.log(p) - np.log1p(-p)

    def potentials(self, points: ArrayLike, directions: ArrayLike) -> np.ndarray:
        """(..., C) potentials of configurations ``points`` (..., N, 3) with their directions."""
        self._check_fitted()
        pts = np.asarray(points, dtype=float)
        dirs = np.asarray(directions, dtype=float)
        i, j, k = self.cliques_.T
        cos = triangle_orientation(
            pts[..., i, :], pts[..., j, :], pts[..., k, :],
            dirs[..., i, :], dirs[..., j, :], dirs[..., k, :],
        )  # fmt: skip
        return _cost(cos, self.reference_, self.penalty_)

    def tables(
        self, candidates: ArrayLike, directions: ArrayLike, *, chunk_size: int = 16
    ) -> np.ndarray:
        """Potentials of every candidate triple of every clique.

        The potential of a clique is ``(1 - r_c cos) / 2`` times its penalty: 0 when the
        triangle faces the learned way squarely, the whole log-odds when it faces the other
        way, half of it when the orientation is undecided (a degenerate triple).

        Parameters
        ----------
        candidates : (N, L, 3) float array, mm
        directions : (N, L, 3) float array
            Boundary directions at the candidates.
        chunk_size : int
            Cliques evaluated together (bounds the working memory, 24 L^3 bytes each).

        Returns
        -------
        (C, L, L, L) float32 array, indexed like :meth:`TripletPrior.potential_tables`.
        """
        self._check_fitted()
        cand = np.asarray(candidates, dtype=float)
        dirs = np.asarray(directions, dtype=float)
        if cand.ndim != 3 or cand.shape[-1] != 3 or dirs.shape != cand.shape:
            raise ParameterError(
                f"`candidates` and `directions` must both have shape (N, L, 3); got "
                f"{cand.shape} and {dirs.shape}"
            )
        n_lab = cand.shape[1]
        out = np.empty((len(self.cliques_), n_lab, n_lab, n_lab), dtype=np.float32)
        penalty = self.penalty_
        for start in range(0, len(self.cliques_), int(chunk_size)):
            sl = slice(start, start + int(chunk_size))
            i, j, k = self.cliques_[sl].T
            cos = _orientation_grid(cand[i], cand[j], cand[k], dirs[i], dirs[j], dirs[k])
            out[sl] = _cost(
                cos, self.reference_[sl, None, None, None], penalty[sl, None, None, None]
            )
        return out

    # ------------------------------------------------------------------ persistence
    FORMAT = "medseg.shape.OrientationPrior"
    FORMAT_VERSION = 1

    def save(self, path) -> Path:
        """Write the fitted term to one ``.npz`` file (:func:`medseg.io.save_arrays`)."""
        self._check_fitted()
        arrays = {
            "cliques": self.cliques_,
            "reference": self.reference_,
            "agreement": self.agreement_,
            "n_training_shapes": np.array(self.n_training_shapes_),
            "pseudo_count": np.array(float(self.pseudo_count)),
        }
        header = {"format": self.FORMAT, "format_version": self.FORMAT_VERSION}
        return save_arrays(path, arrays, header=header)

    @classmethod
    def load(cls, path) -> OrientationPrior:
        """Read a term written by :meth:`save` (or a model folder's headerless file of
        format versions 2-3); ``ModelFileError`` if the file is not one."""
        header, state = load_arrays(path, what="handedness term")
        check_format(
            header, format=cls.FORMAT, version=cls.FORMAT_VERSION, source=str(path),
            missing_ok=True,
        )  # fmt: skip
        try:
            prior = cls(pseudo_count=float(state["pseudo_count"]))
            cliques = np.asarray(state["cliques"], dtype=np.int64)
            reference = np.asarray(state["reference"], dtype=float)
            agreement = np.asarray(state["agreement"], dtype=float)
            n_training = int(state["n_training_shapes"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{path} is incomplete or corrupt ({exc})") from None
        n_c = len(cliques)
        if cliques.shape != (n_c, 3) or reference.shape != (n_c,) or agreement.shape != (n_c,):
            raise ModelFileError(f"{path}: orientation arrays of inconsistent shapes")
        if not (np.all(np.abs(reference) == 1) and np.all((agreement > 0) & (agreement < 1))):
            raise ModelFileError(f"{path}: orientation arrays out of range")
        prior.cliques_, prior.reference_, prior.agreement_ = cliques, reference, agreement
        prior.n_training_shapes_ = n_training
        return prior
