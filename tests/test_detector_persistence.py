"""Detector folders of format version 2: the forests as plain arrays (``forests.npz``).

The round trip must give the same probabilities bit for bit, load nothing through pickle or
skops, keep reading version-1 (skops) folders, and turn every damaged or forged arrays file
into one ModelFileError. (The general save / load behaviour is tested in test_detection.py.)
"""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import skops.io as sio
from sklearn.ensemble import RandomForestClassifier
from sklearn.tree._tree import TREE_LEAF
from test_detection import make_blob

from medseg.detection import FeatureSettings, LandmarkDetector
from medseg.detection import _forest_arrays as forest_arrays
from medseg.detection import _tree_layout as tree_layout
from medseg.detection._persistence import save_detector
from medseg.errors import ModelFileError
from medseg.io import load_arrays, save_arrays


@pytest.fixture(scope="module")
def blobs():
    rng = np.random.default_rng(11)
    return [make_blob(rng, size=(28, 28, 28)) for _ in range(4)]


def _fit(blobs, **kwargs):
    settings = FeatureSettings(scales_mm=(1.0, 2.0), shell_radii_mm=(3.0,))
    detector = LandmarkDetector(
        features=settings, n_estimators=4, n_negative=80, n_mining_pool=1500, random_state=0,
        **kwargs,
    )  # fmt: skip
    return detector.fit([b[0] for b in blobs[:3]], [b[1] for b in blobs[:3]])


@pytest.fixture(scope="module")
def context_detector(blobs):
    """Random forests, the cascade's region forest, auto-context (a stage-1 detector)."""
    return _fit(blobs, auto_context=True)


@pytest.fixture(scope="module")
def extra_detector(blobs):
    return _fit(blobs, forest="extra_trees", n_mining_rounds=0)


def _saved(detector, path):
    return save_detector(detector, path, format_version=2)


def _forests(detector):
    """Every forest of ``detector`` and of its stage 1, the region forests included."""
    out = list(detector.forests_) + [detector.region_forest_] * (
        detector.region_forest_ is not None
    )
    return out + (_forests(detector.stage1_) if detector.stage1_ is not None else [])


def _rows(n_features, n=3000):
    rng = np.random.default_rng(5)
    X = rng.normal(0.5, 1.0, size=(n, n_features)).astype(np.float32)
    X[rng.random(X.shape) < 0.02] = np.nan  # missing values follow each split's direction
    return X


def _assert_same_forests(a_forests, b_forests):
    assert len(a_forests) == len(b_forests)
    for a, b in zip(a_forests, b_forests, strict=True):
        assert type(a) is type(b) and a.get_params() == b.get_params()
        X = _rows(a.n_features_in_)
        assert np.array_equal(a.predict_proba(X), b.predict_proba(X))
        assert np.array_equal(a.classes_, b.classes_) and a.classes_.dtype == b.classes_.dtype
        # the same fitted attributes, of the same types (training statistics aside)
        assert set(vars(a)) - {"_sample_weight"} == set(vars(b)) - {"_sample_weight"}
        for ta, tb in zip(a.estimators_, b.estimators_, strict=True):
            assert ta.get_params() == tb.get_params()
            assert {k: type(v) for k, v in vars(ta).items()} == {
                k: type(v) for k, v in vars(tb).items()
            }
            assert ta.tree_.max_depth == tb.tree_.max_depth
            assert np.array_equal(ta.tree_.children_left, tb.tree_.children_left)


@pytest.mark.parametrize("which", ["context_detector", "extra_detector"])
def test_round_trip_gives_identical_probabilities(which, request, blobs, tmp_path, monkeypatch):
    detector = request.getfixturevalue(which)
    path = save_detector(detector, tmp_path / "det", format_version=2)
    meta = json.loads((path / "detector.json").read_text())
    assert meta["version"] == 2 and (path / "forests.npz").is_file()
    assert not list(path.rglob("*.skops"))
    if detector.auto_context:
        assert (path / "stage1" / "forests.npz").is_file()

    def refuse(*args, **kwargs):
        raise AssertionError("skops was used to load a version-2 detector")

    monkeypatch.setattr(sio, "load", refuse)
    loaded = LandmarkDetector.load(path)
    _assert_same_forests(_forests(detector), _forests(loaded))
    a = detector.candidates(blobs[3][0], n_candidates=4)
    b = loaded.candidates(blobs[3][0], n_candidates=4)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.probabilities, b.probabilities)
    # statistics that are not stored are marked as missing, not made up
    assert np.isnan(loaded.forests_[0].feature_importances_).all()


def test_version_1_folder_still_loads(context_detector, tmp_path):
    path = save_detector(context_detector, tmp_path / "det", format_version=1)
    assert json.loads((path / "detector.json").read_text())["version"] == 1
    assert (path / "forests.skops").is_file() and (path / "stage1" / "forests.skops").is_file()
    assert not list(path.rglob("*.npz"))
    loaded = LandmarkDetector.load(path)
    _assert_same_forests(_forests(context_detector), _forests(loaded))
    # and a version-1 detector re-saved is a version-2 one
    save_detector(loaded, tmp_path / "again", format_version=2)
    assert (tmp_path / "again" / "forests.npz").is_file()


def test_forest_arrays_cannot_store_falls_back_to_skops(extra_detector, tmp_path):
    odd = copy.deepcopy(extra_detector)
    odd.forests_[0].class_weight = {0: 1.0, 1: 3.0}  # int keys: not JSON
    with pytest.warns(UserWarning, match="skops"):
        path = _saved(odd, tmp_path / "det")
    assert json.loads((path / "detector.json").read_text())["version"] == 1
    _assert_same_forests(_forests(odd), _forests(LandmarkDetector.load(path)))


# ----------------------------------------------------------------------- damaged or forged
def _forge(path, edit):
    """Rewrite ``forests.npz`` of the detector folder ``path`` with ``edit(header, arrays)``."""
    file = path / "forests.npz"
    header, arrays = load_arrays(file, what="forests")
    edit(header, arrays)
    save_arrays(file, arrays, header=header)


def _first_split(arrays):
    return int(np.flatnonzero(arrays["left"])[0])


def _set(name, index, value):
    def edit(header, arrays):
        at = _first_split(arrays) if index == "split" else index
        arrays[name] = arrays[name].copy()
        arrays[name][at] = value

    return edit


def _forge_twice_reached(header, arrays):
    # the root's right child pointed at its left child: one node, two parents
    arrays["right"] = arrays["right"].copy()
    arrays["right"][0] = arrays["left"][0]


FORGERIES = {
    "child-outside-tree": (_set("right", "split", 10**6), "outside its tree"),
    "child-before-parent": (_set("left", "split", -1), "outside its tree"),
    "two-parents": (_forge_twice_reached, "child of exactly one node"),
    "feature-out-of-range": (_set("feature", 0, 999), "feature out of range"),
    "depth-understated": (_set("max_depth", 0, 1), "depths do not match"),
    "leaf-value-nan": (_set("values", 0, np.nan), "leaf values"),
    "missing-array": (lambda h, a: a.pop("threshold"), "'threshold' is missing"),
    "wrong-dtype": (lambda h, a: a.update(left=a["left"].astype(np.int64)), "dtype"),
    "extra-tree": (lambda h, a: h["forests"][0].update(n_trees=5), "offsets"),
    "unknown-class": (lambda h, a: h["forests"][0].update({"class": "os.system"}), "class"),
    "bad-parameter": (lambda h, a: h["forests"][0]["params"].update(evil=1), "corrupt"),
    "newer-format": (lambda h, a: h.update(format_version=99), "format version 99"),
}


@pytest.mark.parametrize("forgery", sorted(FORGERIES))
def test_forged_arrays_file_gives_one_clear_error(forgery, extra_detector, tmp_path):
    path = _saved(extra_detector, tmp_path / "det")
    edit, words = FORGERIES[forgery]
    _forge(path, edit)
    with pytest.raises(ModelFileError, match="forests.npz") as info:
        LandmarkDetector.load(path)
    message = str(info.value)
    assert words in message and "\n" not in message, message


@pytest.mark.parametrize("damage", ["truncated", "garbage", "zeroed"])
def test_damaged_arrays_file_gives_model_file_error(damage, extra_detector, tmp_path):
    path = _saved(extra_detector, tmp_path / "det")
    file = path / "forests.npz"
    data = bytearray(file.read_bytes())
    if damage == "truncated":
        file.write_bytes(bytes(data[: len(data) // 2]))
    elif damage == "garbage":
        file.write_bytes(b"not a zip file at all")
    else:
        middle = len(data) // 2
        data[middle : middle + 64] = bytes(64)
        file.write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match="forests.npz"):
        LandmarkDetector.load(path)


def test_any_flipped_byte_loads_the_same_forests_or_is_refused(extra_detector, tmp_path):
    """Bad deflate data, forged zip flags, a broken CRC: a ModelFileError, never another
    exception; a flip the zip format does not protect (a timestamp) changes nothing."""
    path = _saved(extra_detector, tmp_path / "det")
    file = path / "forests.npz"
    data = file.read_bytes()
    rng = np.random.default_rng(0)
    for at in rng.choice(len(data), size=60, replace=False):
        damaged = bytearray(data)
        damaged[at] ^= 0xFF
        file.write_bytes(bytes(damaged))
        try:
            loaded = LandmarkDetector.load(path)
        except ModelFileError:
            continue
        X = _rows(loaded.n_features_, n=200)
        for a, b in zip(_forests(extra_detector), _forests(loaded), strict=True):
            assert np.array_equal(a.predict_proba(X), b.predict_proba(X))


def test_region_flag_must_match_the_forests(context_detector, tmp_path):
    path = _saved(context_detector, tmp_path / "det")
    meta = json.loads((path / "detector.json").read_text())
    meta["fitted"]["region_forest"] = "yes"
    (path / "detector.json").write_text(json.dumps(meta))
    with pytest.raises(ModelFileError, match="region forest"):
        LandmarkDetector.load(path)


def test_changed_sklearn_tree_layout_is_a_clear_error(extra_detector, tmp_path, monkeypatch):
    path = _saved(extra_detector, tmp_path / "det")
    fields = dict(tree_layout.NODE_DTYPE.fields)
    changed = np.dtype(
        [(name, fields[name][0]) for name in tree_layout.NODE_DTYPE.names]
        + [("new_field", np.float64)]
    )
    tree_layout.layout_problem.cache_clear()
    monkeypatch.setattr(tree_layout, "NODE_DTYPE", changed)
    try:
        with pytest.raises(
            ModelFileError, match=r"forests\.npz.*installed scikit-learn.*new_field"
        ):
            LandmarkDetector.load(path)
        with pytest.warns(UserWarning, match="skops"):  # saving falls back to format 1
            save_detector(extra_detector, tmp_path / "det1", format_version=2)
    finally:
        tree_layout.layout_problem.cache_clear()


def test_malformed_tree_in_a_skops_forest_is_refused():
    """Tree.__setstate__ takes children out of range; a forged skops file must not."""
    rng = np.random.default_rng(0)
    X = rng.normal(size=(200, 4))
    forest = RandomForestClassifier(n_estimators=2, max_depth=3, random_state=0)
    forest.fit(X, X[:, 0] > 0)
    forest_arrays.check_forests([forest], "forests.skops")  # a sound forest passes
    state = forest.estimators_[1].tree_.__getstate__()
    split = np.flatnonzero(state["nodes"]["left_child"] != TREE_LEAF)
    state["nodes"]["right_child"][split[0]] = 10**6
    forest.estimators_[1].tree_.__setstate__(state)
    with pytest.raises(ModelFileError, match="malformed tree"):
        forest_arrays.check_forests([forest], "forests.skops")
