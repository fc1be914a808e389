"""A fitted histogram gradient boosting classifier as plain scikit-learn trees.

:class:`sklearn.ensemble.HistGradientBoostingClassifier` learns fast, but its fitted state
(binning, loss object, Cython predictors) has no pickle-free storage, and on one thread its
``predict_proba`` is several times slower than evaluating the same trees as
``sklearn.tree._tree.Tree`` objects. :class:`BoostedTrees` keeps only what prediction reads:
each boosting iteration's regression tree per class (a ``Tree`` with one value per leaf,
``x[feature] <= threshold`` goes left, NaN where the boosting sent it), the baseline, and
the link (logistic for two classes, softmax for more). Its probabilities are those of the
estimator it came from on float32 features (both compare them in double): equal for more
than two classes, to rounding (1e-15) for two.
:mod:`medseg.detection._forest_arrays` stores it like the forests.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from sklearn.ensemble import HistGradientBoostingClassifier
from sklearn.tree._tree import NODE_DTYPE, TREE_LEAF, TREE_UNDEFINED, Tree

from medseg.detection._tree_layout import check_tree_layout
from medseg.errors import ParameterError

__all__ = ["BoostedTrees"]


class BoostedTrees:
    """The trees, baseline and classes of a fitted gradient boosting classifier.

    Attributes
    ----------
    trees_ : list of sklearn.tree._tree.Tree
        Iteration by iteration, ``n_trees_per_iteration_`` trees each (one per class, or
        one for two classes); leaf values are the raw scores they add.
    baseline_ : (n_trees_per_iteration_,) float array
        The raw score before any tree.
    classes_ : (K,) array
    n_features_in_ : int
    """

    def __init__(self, trees, baseline: ArrayLike, classes: ArrayLike, n_features: int):
        self.trees_ = list(trees)
        self.baseline_ = np.asarray(baseline, dtype=np.float64).ravel()
        self.classes_ = np.asarray(classes)
        self.n_features_in_ = int(n_features)
        expected = 1 if len(self.classes_) == 2 else len(self.classes_)
        if len(self.classes_) < 2 or len(self.baseline_) != expected:
            raise ParameterError(
                f"{len(self.classes_)} classes need {expected} trees per iteration; "
                f"the baseline has {len(self.baseline_)}"
            )
        if len(self.trees_) % expected:
            raise ParameterError(f"{len(self.trees_)} trees is not a whole number of iterations")

    @property
    def n_trees_per_iteration_(self) -> int:
        return len(self.baseline_)

    @classmethod
    def from_estimator(cls, estimator: HistGradientBoostingClassifier) -> BoostedTrees:
        """The trees of a fitted ``HistGradientBoostingClassifier`` on numerical features."""
        check_tree_layout(source="a boosting classifier's trees")
        if getattr(estimator, "_preprocessor", None) is not None:
            raise ParameterError("categorical features are not supported")
        trees = [
            _tree(predictor.nodes, estimator.n_features_in_)
            for iteration in estimator._predictors
            for predictor in iteration
        ]
        return cls(
            trees, estimator._baseline_prediction, estimator.classes_, estimator.n_features_in_
        )

    def decision_function(self, X: ArrayLike) -> np.ndarray:
        """(n, n_trees_per_iteration_) raw scores: the baseline plus every tree's leaf."""
        X = np.ascontiguousarray(X, dtype=np.float32)
        if X.ndim != 2 or X.shape[1] != self.n_features_in_:
            raise ParameterError(f"`X` must be (n, {self.n_features_in_}); got {X.shape}")
        k = self.n_trees_per_iteration_
        raw = np.tile(self.baseline_, (len(X), 1))
        for t, tree in enumerate(self.trees_):
            raw[:, t % k] += tree.predict(X)[:, 0]
        return raw

    def predict_proba(self, X: ArrayLike) -> np.ndarray:
        """(n, K) class probabilities, columns in the order of ``classes_``."""
        raw = self.decision_function(X)
        if raw.shape[1] == 1:  # two classes: the logistic of the second's score
            positive = 1.0 / (1.0 + np.exp(-raw[:, 0]))
            return np.stack([1.0 - positive, positive], axis=1)
        raw -= raw.max(axis=1, keepdims=True)
        np.exp(raw, out=raw)
        raw /= raw.sum(axis=1, keepdims=True)
        return raw


def _tree(nodes: np.ndarray, n_features: int) -> Tree:
    """One boosting predictor's nodes as a regression ``Tree`` (one value per leaf)."""
    if np.any(nodes["is_categorical"]):
        raise ParameterError("categorical splits are not supported")
    leaf = nodes["is_leaf"].astype(bool)
    out = np.zeros(len(nodes), dtype=NODE_DTYPE)
    # children are unsigned in the predictor's records: cast before -1 can mark a leaf
    out["left_child"] = np.where(leaf, TREE_LEAF, nodes["left"].astype(np.intp))
    out["right_child"] = np.where(leaf, TREE_LEAF, nodes["right"].astype(np.intp))
    out["feature"] = np.where(leaf, TREE_UNDEFINED, nodes["feature_idx"].astype(np.intp))
    out["threshold"] = np.where(leaf, float(TREE_UNDEFINED), nodes["num_threshold"])
    out["missing_go_to_left"] = np.where(leaf, 0, nodes["missing_go_to_left"])
    out["impurity"] = np.nan
    out["weighted_n_node_samples"] = nodes["count"]
    out["n_node_samples"] = nodes["count"]
    tree = Tree(int(n_features), np.array([1], dtype=np.intp), 1)
    tree.__setstate__(
        {
            "max_depth": int(nodes["depth"].max()),
            "node_count": len(nodes),
            "nodes": out,
            "values": nodes["value"].astype(np.float64).reshape(-1, 1, 1),
        }
    )
    return tree
