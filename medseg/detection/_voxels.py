"""A voxel classifier for the boundary: which label each voxel near the shape belongs to.

The landmark detectors must see any pose, so their features are rotation invariant. The
boundary stage runs in the shape's own frame (:mod:`medseg.frame`), where every case is
upright at its mean size; there the classifier may also use what pose would spoil:
directional derivatives along the frame's axes, the frame coordinates, and the signed
distances to the warped template's labels (the shape's own opinion). Intensities are
normalised by the structure's own contrast, the median inside the warped template against
the median of a ring outside it, so that neither the field of view nor the scanner's
scaling enters.

The classifier is a random forest or histogram gradient boosting (scikit-learn), kept as
plain trees (:class:`medseg.detection._boosting.BoostedTrees` for the boosting) and stored
as node arrays (:mod:`medseg.detection._forest_arrays`) like the landmark detectors, so a
model loads without pickle.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk
from numpy.typing import ArrayLike
from scipy import ndimage
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.ensemble import HistGradientBoostingClassifier, RandomForestClassifier
from threadpoolctl import threadpool_limits

from medseg.detection._boosting import BoostedTrees
from medseg.detection._features import FeatureSettings, compute_features, image_array
from medseg.detection._forest_arrays import load_forests, save_forests
from medseg.detection._prediction import forest_proba
from medseg.errors import ModelFileError, NotFittedError, ParameterError

__all__ = [
    "CONTRAST_RING_MM",
    "VoxelClassifier",
    "context_features",
    "voxel_features",
    "VOXEL_FEATURES",
]

#: the rotation-invariant part of the features (:func:`medseg.detection.compute_features`)
VOXEL_FEATURES = FeatureSettings(
    scales_mm=(1.0, 2.0),
    kinds=("intensity", "smoothed", "gradient", "hessian", "log"),
    normalisation="none",
)
_DIRECTIONAL_SCALE_MM = 1.0
#: the smoothed intensity this far (mm) before and after each voxel along the frame's axes
_CONTEXT_MM = (3.0, 6.0)
_CONTEXT_SCALE_MM = 1.5
#: the ring outside the shape (mm) whose median is the background's: how far beyond the
#: shape :func:`voxel_features` reads the union's signed distances
CONTRAST_RING_MM = (1.0, 4.0)


def _contrast(arr: np.ndarray, distance: np.ndarray) -> tuple[float, float]:
    """Centre and scale of the normalisation: the median inside the shape, and its
    distance to the median of the ring just outside (the structure's contrast)."""
    inside = arr[distance < 0]
    ring = arr[(distance > CONTRAST_RING_MM[0]) & (distance <= CONTRAST_RING_MM[1])]
    if inside.size < 10 or ring.size < 10:
        centre = float(np.median(arr))
        scale = float(np.subtract(*np.percentile(arr, [75, 25])))
    else:
        centre = float(np.median(inside))
        scale = abs(centre - float(np.median(ring)))
        if not scale > 1e-6 * max(1.0, abs(centre)):  # no contrast: the spread inside
            scale = float(np.subtract(*np.percentile(inside, [75, 25])))
    return centre, (scale if scale > 0 else 1.0)


def voxel_features(image: sitk.Image, distances: ArrayLike, where: ArrayLike) -> np.ndarray:
    """Features of the voxels ``where`` of an upright image.

    Parameters
    ----------
    image : 3D SimpleITK image
        The image resampled into the shape's frame (identity direction, frame mm).
    distances : (C, Z, Y, X) float array, mm
        Signed distances to the warped template (negative inside): the first one to the
        union of its labels, then one per label. The first also sets the intensity
        normalisation.
    where : (Z, Y, X) bool array
        The voxels to describe.

    Returns
    -------
    (n, F) float32 array
        One row per voxel of ``where`` in ``np.flatnonzero`` order: the normalised
        intensity features of :data:`VOXEL_FEATURES`, the derivatives along the frame's
        axes at 1 mm, the smoothed intensity 3 and 6 mm before and after along each axis,
        the frame coordinates (mm), and ``distances``.
    """
    arr = image_array(image)
    distances = np.asarray(distances, dtype=np.float32)
    where = np.asarray(where, dtype=bool)
    if distances.ndim != 4 or distances.shape[1:] != arr.shape or where.shape != arr.shape:
        raise ParameterError(
            f"`distances` must be (C,) + {arr.shape} and `where` {arr.shape}; got "
            f"{distances.shape} and {where.shape}"
        )
    centre, scale = _contrast(arr, distances[0])
    normalised = sitk.GetImageFromArray((arr - centre) / scale)
    normalised.CopyInformation(image)
    invariant = compute_features(normalised, VOXEL_FEATURES)[where]
    spacing = np.asarray(image.GetSpacing(), dtype=float)[::-1]
    smooth = ndimage.gaussian_filter(
        sitk.GetArrayViewFromImage(normalised), _DIRECTIONAL_SCALE_MM / spacing, mode="nearest"
    )
    directional = np.stack([g[where] for g in np.gradient(smooth, *spacing)], axis=1)
    context = _context(sitk.GetArrayViewFromImage(normalised), spacing, where)
    index = np.argwhere(where)[:, ::-1].astype(float)  # (x, y, z) voxel indices
    origin = np.asarray(image.GetOrigin(), dtype=float)
    coords = origin + index * np.asarray(image.GetSpacing(), dtype=float)
    return np.hstack(
        [invariant, directional * _DIRECTIONAL_SCALE_MM, context, coords, distances[:, where].T]
    ).astype(np.float32)


def _context(
    arr: np.ndarray, spacing: np.ndarray, where: np.ndarray, offsets_mm=_CONTEXT_MM
) -> np.ndarray:
    """(n, 6 * len(offsets_mm)) smoothed values at offsets along each frame axis
    (clamped at the grid's edge): what lies beside a voxel, which only an upright frame
    makes comparable from case to case."""
    smooth = ndimage.gaussian_filter(arr, _CONTEXT_SCALE_MM / spacing, mode="nearest")
    index = np.argwhere(where)
    columns = []
    for axis in range(3):
        for mm in offsets_mm:
            step = int(round(mm / spacing[axis]))
            for sign in (-1, 1):
                moved = index.copy()
                moved[:, axis] = np.clip(moved[:, axis] + sign * step, 0, arr.shape[axis] - 1)
                columns.append(smooth[tuple(moved.T)])
    return np.stack(columns, axis=1)


def context_features(probabilities: ArrayLike, where: ArrayLike, spacing_zyx) -> np.ndarray:
    """Features of a first classifier's answer around each voxel (auto-context).

    Tu & Bai (TPAMI 2010): a second classifier that also sees what the first one said in
    the neighbourhood learns the structure's shape in the large, which single voxels'
    intensities do not show.

    Parameters
    ----------
    probabilities : (n, C) float array
        The first classifier's probabilities over the voxels ``where``, background first.
    where : (Z, Y, X) bool array
    spacing_zyx : (3,) float, mm

    Returns
    -------
    (n, 2 C + 6) float32 array
        The probability of the union and of each label, smoothed at 1 and 3 mm, and the
        union's smoothed at 1.5 mm, 3 mm before and after along each axis.
    """
    probabilities = np.asarray(probabilities, dtype=np.float32)
    where = np.asarray(where, dtype=bool)
    spacing = np.asarray(spacing_zyx, dtype=float)
    maps = [1.0 - probabilities[:, 0]] + [
        probabilities[:, k] for k in range(1, probabilities.shape[1])
    ]
    columns = []
    for values in maps:
        grid = np.zeros(where.shape, dtype=np.float32)
        grid[where] = values
        for sigma_mm in (1.0, 3.0):
            columns.append(ndimage.gaussian_filter(grid, sigma_mm / spacing)[where])
    union = np.zeros(where.shape, dtype=np.float32)
    union[where] = maps[0]
    offsets = _context(union, spacing, where, offsets_mm=(3.0,))
    return np.hstack([np.stack(columns, axis=1), offsets]).astype(np.float32)


class VoxelClassifier(ClassifierMixin, BaseEstimator):
    """Random forest or gradient boosting over :func:`voxel_features`: class probabilities
    of each voxel.

    Parameters
    ----------
    method : {"forest", "boosting"}, default "forest"
        A random forest, or histogram gradient boosting (fitted by scikit-learn, kept as
        :class:`~medseg.detection._boosting.BoostedTrees`).
    n_estimators : int, default 30
        Trees of the forest, or boosting iterations.
    min_samples_leaf : int, default 5
        Of the forest's trees (the boosting keeps scikit-learn's 20).
    max_features : str, int or float, default "sqrt"
        Of the forest's trees.
    learning_rate : float, default 0.1
        Of the boosting.
    max_leaf_nodes : int, default 31
        Of each boosting tree.
    random_state : int, RandomState or None
    n_jobs : int, default 1
        Threads of the fitting and of a forest's prediction; the model does not depend on
        it. A loaded classifier predicts on one thread, whatever threads fitted it.

    Attributes
    ----------
    ensemble_ : RandomForestClassifier or BoostedTrees
    classes_ : (K,) int array
        The label values, 0 (background) first.
    """

    FORMAT = "medseg.detection.VoxelClassifier"
    METHODS = ("forest", "boosting")

    def __init__(
        self,
        method: str = "forest",
        n_estimators: int = 30,
        *,
        min_samples_leaf: int = 5,
        max_features="sqrt",
        learning_rate: float = 0.1,
        max_leaf_nodes: int = 31,
        random_state=None,
        n_jobs: int = 1,
    ):
        self.method = method
        self.n_estimators = n_estimators
        self.min_samples_leaf = min_samples_leaf
        self.max_features = max_features
        self.learning_rate = learning_rate
        self.max_leaf_nodes = max_leaf_nodes
        self.random_state = random_state
        self.n_jobs = n_jobs

    def fit(self, X: ArrayLike, y: ArrayLike) -> VoxelClassifier:
        """Fit on feature rows ``X`` (:func:`voxel_features`) and label values ``y``."""
        X = np.asarray(X, dtype=np.float32)
        y = np.asarray(y).astype(np.int64)
        if self.method not in self.METHODS:
            raise ParameterError(f"`method` must be one of {self.METHODS}; got {self.method!r}")
        if X.ndim != 2 or len(X) != len(y) or len(X) == 0:
            raise ParameterError(f"`X` must be (n, F) with one label each; got {X.shape}")
        if len(np.unique(y)) < 2:
            raise ParameterError("the voxel classifier needs at least two labels among `y`")
        if self.method == "forest":
            self.ensemble_ = RandomForestClassifier(
                n_estimators=self.n_estimators,
                min_samples_leaf=self.min_samples_leaf,
                max_features=self.max_features,
                random_state=self.random_state,
                n_jobs=self.n_jobs,
            ).fit(X, y)
        else:
            boosting = HistGradientBoostingClassifier(
                max_iter=self.n_estimators,
                learning_rate=self.learning_rate,
                max_leaf_nodes=self.max_leaf_nodes,
                early_stopping=False,
                random_state=self.random_state,
            )
            with threadpool_limits(limits=self.n_jobs, user_api="openmp"):
                boosting.fit(X, y)
            self.ensemble_ = BoostedTrees.from_estimator(boosting)
        self.classes_ = self.ensemble_.classes_
        return self

    def predict_proba(self, X: ArrayLike) -> np.ndarray:
        """(n, K) class probabilities, columns in the order of ``classes_``."""
        if not hasattr(self, "ensemble_"):
            raise NotFittedError("this VoxelClassifier is not fitted yet")
        X = np.asarray(X, dtype=np.float32)
        if isinstance(self.ensemble_, RandomForestClassifier):
            self.ensemble_.n_jobs = self.n_jobs  # not the threads stored with the trees
            return forest_proba(self.ensemble_, X)
        return self.ensemble_.predict_proba(X)

    def save(self, path) -> Path:
        """Write the trees to one ``.npz`` file (node arrays, no pickle)."""
        save_forests(path, [self.ensemble_])
        return Path(path)

    @classmethod
    def load(cls, path, **params) -> VoxelClassifier:
        """Read a classifier written by :meth:`save`."""
        ensembles = load_forests(path)
        if len(ensembles) != 1:
            raise ModelFileError(f"{path} holds {len(ensembles)} ensembles, not one")
        ensemble = ensembles[0]
        method = "boosting" if isinstance(ensemble, BoostedTrees) else "forest"
        model = cls(**({"method": method} | params))
        model.ensemble_ = ensemble
        model.classes_ = ensemble.classes_
        return model
