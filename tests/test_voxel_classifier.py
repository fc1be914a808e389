"""The regional stage's voxel classifier: forest or boosting, stored without pickle.

The boosting is fitted by scikit-learn and kept as plain trees (``BoostedTrees``): its
probabilities must be the estimator's, and both methods must come back from their file with
the same probabilities, whatever the label values.
"""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.ensemble import HistGradientBoostingClassifier

from medseg.detection import VoxelClassifier
from medseg.detection._boosting import BoostedTrees
from medseg.errors import ModelFileError, ParameterError
from medseg.io import load_arrays, save_arrays


def _rows(n_classes: int, n: int = 3000, missing: float = 0.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, 8)).astype(np.float32)
    score = X[:, 0] + X[:, 1] * X[:, 2] + 0.3 * rng.normal(size=n)
    y = np.digitize(score, np.quantile(score, np.linspace(0, 1, n_classes + 1)[1:-1]))
    X[rng.random(X.shape) < missing] = np.nan
    return X, y


@pytest.mark.parametrize("n_classes", [2, 3])
def test_boosted_trees_predict_as_the_estimator_does(n_classes):
    X, y = _rows(n_classes, missing=0.05)  # NaN go where the boosting sent them
    estimator = HistGradientBoostingClassifier(
        max_iter=25, early_stopping=False, random_state=0
    ).fit(X[:2000], y[:2000])
    trees = BoostedTrees.from_estimator(estimator)
    assert len(trees.trees_) == 25 * (1 if n_classes == 2 else n_classes)
    np.testing.assert_allclose(
        trees.predict_proba(X[2000:]), estimator.predict_proba(X[2000:]), rtol=0, atol=1e-12
    )


def test_categorical_boosting_is_refused():
    X, y = _rows(2)
    X[:, 0] = np.round(np.abs(X[:, 0]) * 2)
    estimator = HistGradientBoostingClassifier(
        max_iter=3, categorical_features=[0], random_state=0
    ).fit(X, y)
    with pytest.raises(ParameterError, match="categorical"):
        BoostedTrees.from_estimator(estimator)


@pytest.mark.parametrize("method", VoxelClassifier.METHODS)
def test_round_trip_keeps_method_labels_and_probabilities(method, tmp_path):
    X, y = _rows(3)
    y = np.array([0, 3, 7])[y]  # label values that are not the classes' indices
    fitted = VoxelClassifier(method, 10, random_state=0, n_jobs=2).fit(X[:2000], y[:2000])
    loaded = VoxelClassifier.load(fitted.save(tmp_path / "classifier.npz"))
    assert loaded.method == method
    if method == "forest":  # loaded, it predicts on one thread, not the fitting's pool
        loaded.ensemble_.predict_proba = None
    # two threads sum the trees in the order they finish (to 1 ulp): compare on one
    fitted.n_jobs = 1
    np.testing.assert_array_equal(loaded.classes_, [0, 3, 7])
    np.testing.assert_array_equal(loaded.predict_proba(X[2000:]), fitted.predict_proba(X[2000:]))
    # and the classifier learnt something: most held-out rows get their label
    assert np.mean(loaded.classes_[loaded.predict_proba(X[2000:]).argmax(1)] == y[2000:]) > 0.7


def _forge(path, edit):
    header, arrays = load_arrays(path, what="classifier")
    edit(header["forests"][0], arrays)
    save_arrays(path, arrays, header=header)


FORGERIES = {
    "baseline-length": (lambda s, a: s.update(baseline=s["baseline"][:2]), "trees per iteration"),
    "baseline-nan": (lambda s, a: s.update(baseline=[float("nan")] * 3), "baseline"),
    "leaf-width": (lambda s, a: s["tree_fitted"].update(n_classes_=3), "fewer leaf values"),
    "partial-iteration": (lambda s, a: s["fitted"]["classes_"].update(values=[0, 1]), "baseline"),
    "leaf-value-nan": (lambda s, a: a["values"].__setitem__(0, np.nan), "leaf values"),
}


@pytest.mark.parametrize("forgery", sorted(FORGERIES))
def test_a_forged_boosting_file_is_refused_with_one_message(forgery, tmp_path):
    X, y = _rows(3)
    path = VoxelClassifier("boosting", 4, random_state=0).fit(X, y).save(tmp_path / "c.npz")
    edit, words = FORGERIES[forgery]
    _forge(path, edit)
    with pytest.raises(ModelFileError, match="c.npz") as info:
        VoxelClassifier.load(path)
    assert words in str(info.value), str(info.value)


def test_an_unknown_method_is_a_parameter_error():
    X, y = _rows(2)
    with pytest.raises(ParameterError, match="method"):
        VoxelClassifier("svm").fit(X, y)
