"""Scikit-learn forests as plain arrays: how a detector of format version 2 stores its forests.

One NPZ file (:func:`medseg.io.save_arrays`) holds every forest of a detector (or the voxel
classifier's one ensemble: a forest, or a boosting's trees,
:class:`medseg.detection._boosting.BoostedTrees`, whose header also carries its baseline and
whose leaves hold one raw score each). Its JSON header
lists, per forest, the estimator class, its constructor parameters and fitted scalars
(``classes_``, ``n_features_in_``, ...), and the parameters shared by its trees; the arrays hold
all trees of all forests concatenated, in compact dtypes:

==================  =========  ==============================================================
``node_offsets``    int64      first node of each tree, plus the total (``n_trees + 1``)
``max_depth``       int32      depth of each tree
``random_state``    int64      seed of each tree (its ``random_state`` parameter)
``left``            int32      per node: left child minus the node's index; 0 marks a leaf
``right``           int32      the same for the right child
``feature``         int16/32   per split node: the feature it tests
``threshold``       float64    per split node: go left when ``x[feature] <= threshold``
``missing_left``    uint8      per split node: where a missing (NaN) value goes
``values``          float64    per leaf, its class fractions (flattened, ``n_classes`` each)
==================  =========  ==============================================================

That is all ``predict_proba`` reads, and it comes back bit for bit: thresholds and leaf values
stay float64 (as float32, a fifth of the leaf fractions of a real detector change, and the
probabilities with them). The training statistics of a tree are not stored (impurity, sample
counts, the class fractions of split nodes, a forest's ``_sample_weight``): a loaded forest
gives NaN for ``feature_importances_`` and has no ``estimators_samples_``. Nothing in medseg
uses them.

Loading rebuilds real scikit-learn estimators: each tree's ``sklearn.tree._tree.Tree`` is
given its state through ``Tree.__setstate__`` (``max_depth``, ``node_count``, ``nodes`` as a
structured array of the installed ``NODE_DTYPE``, ``values``), as unpickling does. That is the
one scikit-learn internal relied on; :func:`medseg.detection._tree_layout.check_tree_layout`
checks it (the state's keys, the node fields, and a probe tree that must predict as expected)
and raises a :class:`ModelFileError` naming the scikit-learn version if a future release
changes it, rather than rebuilding trees that would predict wrongly. ``Tree.__setstate__``
does not check the nodes it is given (a child index out of range would read outside the
tree's memory), so the arrays are validated first: children after their parent and inside
their tree, every node reached exactly once from its root, features in range, depths as
stored, leaf values finite.
The format, that validation and the rebuild are one idea and stay in one module (over 400
lines for it).
"""

from __future__ import annotations

import json

import numpy as np
import sklearn
from sklearn.ensemble import ExtraTreesClassifier, RandomForestClassifier
from sklearn.tree import DecisionTreeClassifier, ExtraTreeClassifier
from sklearn.tree._tree import NODE_DTYPE, TREE_LEAF, TREE_UNDEFINED, Tree

from medseg.detection._boosting import BoostedTrees
from medseg.detection._tree_layout import TREE_STATE_KEYS, check_tree_layout, layout_problem
from medseg.errors import ModelFileError, ParameterError
from medseg.io import check_format, load_arrays, save_arrays

__all__ = [
    "check_forests",
    "FORMAT",
    "FORMAT_VERSION",
    "UnsupportedForest",
    "load_forests",
    "save_forests",
]

FORMAT = "medseg.detection.forests"
FORMAT_VERSION = 1
_FORESTS = {cls.__name__: cls for cls in (RandomForestClassifier, ExtraTreesClassifier)}
_TREES = {cls.__name__: cls for cls in (DecisionTreeClassifier, ExtraTreeClassifier)}
# fitted attributes of a forest and of a tree, beyond what their constructor sets
_FOREST_FITTED = {
    "n_features_in_", "n_outputs_", "classes_", "n_classes_", "_n_samples",
    "_n_samples_bootstrap", "_sample_weight", "estimator_", "estimators_",
}  # fmt: skip
_TREE_FITTED = {"n_features_in_", "n_outputs_", "classes_", "n_classes_", "max_features_", "tree_"}
_ARRAYS = {  # name -> allowed dtypes
    "node_offsets": ("int64",),
    "max_depth": ("int32",),
    "random_state": ("int64",),
    "left": ("int32",),
    "right": ("int32",),
    "feature": ("int16", "int32"),
    "threshold": ("float64",),
    "missing_left": ("uint8",),
    "values": ("float64",),
}


class UnsupportedForest(Exception):
    """A forest this format cannot store exactly (the caller falls back to skops)."""


# ----------------------------------------------------------------------------------- save
def _json_exact(value) -> bool:
    """Whether ``value`` comes back from JSON equal and of the same types."""
    if value is None or isinstance(value, bool | str):
        return True
    if isinstance(value, int | float):
        return type(value) in (int, float) and json.loads(json.dumps(value)) == value
    if isinstance(value, list):
        return all(_json_exact(v) for v in value)
    if isinstance(value, dict):
        return all(isinstance(k, str) and _json_exact(v) for k, v in value.items())
    return False


def _classes(classes) -> dict:
    classes = np.asarray(classes)
    if classes.ndim != 1 or classes.dtype.kind not in "biuf":
        raise UnsupportedForest(f"classes_ of dtype {classes.dtype} and shape {classes.shape}")
    return {"values": classes.tolist(), "dtype": classes.dtype.str}


def _trees(forest) -> list:
    """The ``Tree`` objects of a forest or of :class:`BoostedTrees`, in storage order."""
    if isinstance(forest, BoostedTrees):
        return list(forest.trees_)
    return [estimator.tree_ for estimator in forest.estimators_]


def _seeds(forest) -> list:
    if isinstance(forest, BoostedTrees):
        return [0] * len(forest.trees_)
    return [estimator.random_state for estimator in forest.estimators_]


def _boosting_spec(boosted: BoostedTrees) -> dict:
    n_features = int(boosted.n_features_in_)
    if not boosted.trees_ or any(
        t.n_features != n_features or list(t.n_classes) != [1] or t.n_outputs != 1
        for t in boosted.trees_
    ):
        raise UnsupportedForest("boosting trees of another shape than one score per leaf")
    baseline = [float(v) for v in boosted.baseline_]
    if not np.isfinite(baseline).all():
        raise UnsupportedForest("a baseline that is not finite")
    return {
        "class": "BoostedTrees",
        "fitted": {"n_features_in_": n_features, "classes_": _classes(boosted.classes_)},
        "baseline": baseline,
        "tree_fitted": {"n_features_in_": n_features, "n_classes_": 1},
        "n_trees": len(boosted.trees_),
    }


def _forest_spec(forest) -> dict:
    """The JSON description of ``forest`` and its trees (everything but the node arrays)."""
    if isinstance(forest, BoostedTrees):
        return _boosting_spec(forest)
    cls = type(forest)
    if _FORESTS.get(cls.__name__) is not cls:
        raise UnsupportedForest(f"{cls.__name__} is not a plain random / extra-trees forest")
    params = forest.get_params(deep=False)
    if not _json_exact(params):
        raise UnsupportedForest(f"parameters {params} do not survive JSON")
    unknown = set(vars(forest)) - set(vars(cls(**params))) - _FOREST_FITTED
    if unknown or int(forest.n_outputs_) != 1:
        raise UnsupportedForest(f"fitted attributes {sorted(unknown)} or several outputs")
    trees = list(forest.estimators_)
    if not trees:
        raise UnsupportedForest("a forest without trees")
    tree_cls = type(trees[0])
    tree_params = trees[0].get_params(deep=False)
    tree_params.pop("random_state")
    tree_fitted = {
        "n_features_in_": int(trees[0].n_features_in_),
        "n_outputs_": int(trees[0].n_outputs_),
        "classes_": _classes(trees[0].classes_),
        "n_classes_": int(trees[0].n_classes_),
        "max_features_": int(trees[0].max_features_),
    }
    reference = set(vars(tree_cls(**tree_params))) | _TREE_FITTED
    for tree in trees:
        params_i = tree.get_params(deep=False)
        seed = params_i.pop("random_state")
        same = (
            type(tree) is tree_cls
            and params_i == tree_params
            and set(vars(tree)) <= reference
            and type(seed) is int
            and int(tree.n_features_in_) == tree_fitted["n_features_in_"]
            and int(tree.n_outputs_) == 1
            and int(tree.n_classes_) == tree_fitted["n_classes_"]
            and int(tree.max_features_) == tree_fitted["max_features_"]
            and _classes(tree.classes_) == tree_fitted["classes_"]
            and tree.tree_.n_features == tree.n_features_in_
            and list(tree.tree_.n_classes) == [tree_fitted["n_classes_"]]
        )
        if not same:
            raise UnsupportedForest("trees of one forest differ in class, parameters or shape")
    if _TREES.get(tree_cls.__name__) is not tree_cls or not _json_exact(tree_params):
        raise UnsupportedForest(f"trees of class {tree_cls.__name__} or parameters {tree_params}")
    fitted = {
        "n_features_in_": int(forest.n_features_in_),
        "n_outputs_": 1,
        "classes_": _classes(forest.classes_),
        "n_classes_": int(forest.n_classes_),
    }
    for name in ("_n_samples", "_n_samples_bootstrap"):
        if name in vars(forest):
            value = getattr(forest, name)
            fitted[name] = None if value is None else int(value)
    return {
        "class": cls.__name__,
        "params": params,
        "fitted": fitted,
        "tree_class": tree_cls.__name__,
        "tree_params": tree_params,
        "tree_fitted": tree_fitted,
        "n_trees": len(trees),
    }


def _tree_arrays(tree: Tree) -> dict:
    state = tree.__getstate__()
    if set(state) != set(TREE_STATE_KEYS):
        raise UnsupportedForest(f"tree state with keys {sorted(state)}")
    nodes, values = state["nodes"], state["values"]
    n = int(state["node_count"])
    left = nodes["left_child"].astype(np.int64)
    right = nodes["right_child"].astype(np.int64)
    split = left != TREE_LEAF
    index = np.arange(n)
    if (
        nodes.shape != (n,)
        or not np.array_equal(split, right != TREE_LEAF)
        or np.any(left[split] <= index[split])
        or np.any(right[split] <= index[split])
    ):
        raise UnsupportedForest("a tree whose children do not follow their parent")
    return {
        "n": n,
        "max_depth": int(state["max_depth"]),
        "left": np.where(split, left - index, 0).astype(np.int32),
        "right": np.where(split, right - index, 0).astype(np.int32),
        "feature": nodes["feature"][split],
        "threshold": nodes["threshold"][split].astype(np.float64),
        "missing_left": nodes["missing_go_to_left"][split].astype(np.uint8),
        "values": values[~split, 0, :].ravel(),
    }


def _node_arrays(forests) -> dict:
    """The node arrays of every tree of ``forests``, concatenated (all but ``random_state``)."""
    trees = [_tree_arrays(t) for f in forests for t in _trees(f)]
    n_features = max((int(f.n_features_in_) for f in forests), default=0)
    feature_dtype = np.int16 if n_features <= np.iinfo(np.int16).max else np.int32
    dtypes = {
        "left": np.int32,
        "right": np.int32,
        "feature": feature_dtype,
        "threshold": np.float64,
        "missing_left": np.uint8,
        "values": np.float64,
    }
    arrays = {
        name: np.concatenate([t[name] for t in trees]).astype(dtype)
        if trees
        else np.zeros(0, dtype=dtype)
        for name, dtype in dtypes.items()
    }
    arrays["node_offsets"] = np.cumsum([0] + [t["n"] for t in trees], dtype=np.int64)
    arrays["max_depth"] = np.array([t["max_depth"] for t in trees], dtype=np.int32)
    return arrays


def save_forests(path, forests) -> None:
    """Write ``forests`` (a list of fitted forests) to the NPZ file ``path``.

    Raises
    ------
    UnsupportedForest
        A forest this format cannot store exactly (another class, several outputs, parameters
        that JSON cannot carry, unknown fitted attributes, or an installed scikit-learn whose
        tree layout is unknown). Nothing is written.
    """
    if layout_problem():
        raise UnsupportedForest(layout_problem())
    specs = [_forest_spec(f) for f in forests]
    arrays = _node_arrays(forests)
    arrays["random_state"] = np.array([s for f in forests for s in _seeds(f)], dtype=np.int64)
    header = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "sklearn_version": sklearn.__version__,
        "forests": specs,
    }
    save_arrays(path, arrays, header=header)


def check_forests(forests, source) -> None:
    """Check the trees of forests read otherwise (skops) as :func:`load_forests` does.

    ``Tree.__setstate__`` takes any node array of the right dtype, so a forged file could
    point a child outside its tree; this refuses such trees before they predict.

    Raises
    ------
    ModelFileError
        A tree's nodes do not form a tree, or test features out of range.
    """
    try:
        arrays = _node_arrays(forests)
        arrays["random_state"] = np.zeros(len(arrays["max_depth"]), dtype=np.int64)
        for _ in _forest_parts(
            arrays,
            [len(f.estimators_) for f in forests],
            [int(f.n_features_in_) for f in forests],
            [int(f.estimators_[0].tree_.n_classes[0]) if f.estimators_ else 1 for f in forests],
        ):
            pass
    except (UnsupportedForest, ModelFileError) as exc:
        raise ModelFileError(
            f"load: {source} holds a malformed tree ({exc}); refusing to use it"
        ) from None


def load_forests(path) -> list:
    """Read the forests written by :func:`save_forests` as scikit-learn estimators.

    Raises
    ------
    InputFileError
        The file does not exist.
    ModelFileError
        The file is truncated, corrupt, forged or of a newer format, or the installed
        scikit-learn stores trees differently (:func:`check_tree_layout`). One message, naming
        the file.
    """
    header, arrays = load_arrays(path, what="detector forests")
    check_format(header, format=FORMAT, version=FORMAT_VERSION, source=str(path))
    check_tree_layout(header.get("sklearn_version"), str(path))
    try:
        return _rebuild(header["forests"], arrays)
    except ModelFileError as exc:
        raise ModelFileError(f"{path}: {exc}; the file is corrupt or forged") from None
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, OverflowError) as exc:
        raise ModelFileError(
            f"{path} is corrupt or incomplete ({type(exc).__name__}: {exc}); re-save the detector"
        ) from None


def _forest_parts(arrays: dict, n_trees: list[int], n_features: list[int], n_classes: list[int]):
    """Per forest, its slices of the arrays, after every check that makes them safe to hand
    to ``Tree.__setstate__`` (a generator: each forest is checked as it is reached).

    ``n_trees``, ``n_features`` and ``n_classes`` are per forest. Yields dicts of the
    forest's ``offsets`` (of its trees, from 0), ``split`` (bool per node), ``left`` /
    ``right`` (child indices within the forest's nodes, -1 at leaves), ``feature``,
    ``threshold``, ``missing_left`` (per split node), ``values`` ((n_leaves, n_classes)),
    ``max_depth`` and ``random_state`` (per tree).
    """
    for name, dtypes in _ARRAYS.items():
        if name not in arrays:
            raise ModelFileError(f"the array {name!r} is missing")
        if arrays[name].ndim != 1 or arrays[name].dtype.name not in dtypes:
            raise ModelFileError(f"the array {name!r} has dtype {arrays[name].dtype}")
    a = {name: arrays[name] for name in _ARRAYS}
    offsets = a["node_offsets"]
    n_total = int(sum(n_trees))
    n_nodes = len(a["left"])
    if (
        offsets.shape != (n_total + 1,)
        or offsets[0] != 0
        or offsets[-1] != n_nodes
        or np.any(np.diff(offsets) < 1)
        or len(a["right"]) != n_nodes
        or len(a["max_depth"]) != n_total
        or len(a["random_state"]) != n_total
    ):
        raise ModelFileError("the tree offsets do not match the node arrays")
    if any(len(a[name]) > n_nodes for name in ("feature", "threshold", "missing_left")):
        raise ModelFileError("more split nodes than nodes")
    tree, split_at, value_at = 0, 0, 0
    for n_t, n_f, n_c in zip(n_trees, n_features, n_classes, strict=True):
        lo, hi = int(offsets[tree]), int(offsets[tree + n_t])
        split = a["left"][lo:hi] != 0
        if not np.array_equal(split, a["right"][lo:hi] != 0):
            raise ModelFileError("split nodes and their arrays do not match")
        s_lo, s_hi = split_at, split_at + int(np.count_nonzero(split))
        part = {
            "offsets": (offsets[tree : tree + n_t + 1] - lo).astype(np.int32),
            "split": split,
            "feature": a["feature"][s_lo:s_hi],
            "threshold": a["threshold"][s_lo:s_hi],
            "missing_left": a["missing_left"][s_lo:s_hi],
            "max_depth": a["max_depth"][tree : tree + n_t],
            "random_state": a["random_state"][tree : tree + n_t],
        }
        if any(len(part[name]) != s_hi - s_lo for name in ("feature", "threshold", "missing_left")):
            raise ModelFileError("split nodes and their arrays do not match")
        n_values = (hi - lo - (s_hi - s_lo)) * n_c
        values = a["values"][value_at : value_at + n_values]
        if n_c < 1 or len(values) != n_values:
            raise ModelFileError("fewer leaf values than leaves")
        part["values"] = values.reshape(-1, n_c)
        part["left"], part["right"] = _checked_children(
            a["left"][lo:hi], a["right"][lo:hi], split, part["offsets"], part["max_depth"]
        )
        feature = part["feature"]
        if feature.size and (feature.min() < 0 or feature.max() >= n_f):
            raise ModelFileError("a split tests a feature out of range")
        if np.any(part["missing_left"] > 1) or not np.isfinite(values).all():
            raise ModelFileError("invalid missing-value directions or leaf values")
        yield part
        tree, split_at, value_at = tree + n_t, s_hi, value_at + n_values
    if split_at != len(a["feature"]) or value_at != len(a["values"]):
        raise ModelFileError("the arrays hold more split nodes or leaf values than the trees")


def _checked_children(left, right, split, offsets, max_depth):
    """Child indices (within each tree, -1 at leaves, int32) from the stored offsets, once
    the nodes are known to form trees: every child after its parent and inside its tree,
    every node but the roots the child of exactly one node, the depths as stored."""
    n_nodes, n_trees = len(split), len(offsets) - 1
    node = np.flatnonzero(split).astype(np.int32)
    tree_of = np.repeat(np.arange(n_trees, dtype=np.int32), np.diff(offsets))
    room = offsets[1:][tree_of[node]] - node  # how far a child may lie after its parent
    step_left, step_right = left[node], right[node]
    if (
        np.any(step_left <= 0)
        or np.any(step_right <= 0)
        or np.any(step_left >= room)
        or np.any(step_right >= room)
    ):
        raise ModelFileError("a child node lies outside its tree")
    child_left, child_right = node + step_left, node + step_right
    parents = np.bincount(np.concatenate([child_left, child_right]), minlength=n_nodes)
    roots = offsets[:-1]
    if np.any(parents[roots]) or np.count_nonzero(parents == 1) != n_nodes - n_trees:
        raise ModelFileError("a node is not the child of exactly one node")
    full_left = np.full(n_nodes, TREE_LEAF, dtype=np.int32)
    full_right = np.full(n_nodes, TREE_LEAF, dtype=np.int32)
    full_left[node], full_right[node] = child_left, child_right
    # breadth first from the roots: the deepest level reached is the tree's depth
    depth = np.zeros(n_trees, dtype=np.int64)
    frontier, level = roots, 0
    while frontier.size:
        depth[tree_of[frontier]] = level
        inner = frontier[split[frontier]]
        frontier = np.concatenate([full_left[inner], full_right[inner]])
        level += 1
    if not np.array_equal(depth, max_depth):
        raise ModelFileError("the stored tree depths do not match the trees")
    # as scikit-learn's trees index their nodes: from each tree's first node
    start = roots[tree_of[node]]
    full_left[node] -= start
    full_right[node] -= start
    return full_left, full_right


def _classes_array(spec: dict) -> np.ndarray:
    dtype = np.dtype(spec["dtype"])
    if dtype.kind not in "biuf":
        raise ModelFileError(f"classes of dtype {dtype}")
    return np.array(spec["values"], dtype=dtype)


def _rebuild(specs: list, arrays: dict) -> list:
    if not isinstance(specs, list) or not all(isinstance(s, dict) for s in specs):
        raise ModelFileError("the header lists no forests")
    parts = _forest_parts(
        arrays,
        [int(s["n_trees"]) for s in specs],
        [int(s["tree_fitted"]["n_features_in_"]) for s in specs],
        [int(s["tree_fitted"]["n_classes_"]) for s in specs],
    )
    forests = []
    for spec, part in zip(specs, parts, strict=True):
        if spec["class"] == "BoostedTrees":
            forests.append(_rebuild_boosting(spec, part))
        else:
            forests.append(_rebuild_forest(spec, part))
    return forests


def _rebuild_boosting(spec: dict, part: dict) -> BoostedTrees:
    n_features = int(spec["fitted"]["n_features_in_"])
    if (
        int(spec["tree_fitted"]["n_classes_"]) != 1
        or int(spec["tree_fitted"]["n_features_in_"]) != n_features
    ):
        raise ModelFileError("boosting trees of another shape than one score per leaf")
    baseline = np.asarray(spec["baseline"], dtype=np.float64)
    if baseline.ndim != 1 or not np.isfinite(baseline).all():
        raise ModelFileError("the boosting's baseline is not a finite vector")
    trees = _build_trees(part, n_features, 1)
    try:
        return BoostedTrees(trees, baseline, _classes_array(spec["fitted"]["classes_"]), n_features)
    except ParameterError as exc:
        raise ModelFileError(str(exc)) from None


def _rebuild_forest(spec: dict, part: dict):
    cls, tree_cls = _FORESTS.get(spec["class"]), _TREES.get(spec["tree_class"])
    if cls is None or tree_cls is None:
        raise ModelFileError(f"unknown estimator class {spec['class']!r}")
    fitted, tree_fitted = spec["fitted"], spec["tree_fitted"]
    n_classes, n_features = int(tree_fitted["n_classes_"]), int(tree_fitted["n_features_in_"])
    classes = _classes_array(fitted["classes_"])
    tree_classes = _classes_array(tree_fitted["classes_"])
    if (
        len(classes) != n_classes
        or int(fitted["n_classes_"]) != n_classes
        # a forest's trees learn the classes' indices (scikit-learn encodes ``y``)
        or not np.array_equal(tree_classes, np.arange(n_classes))
        or int(fitted["n_features_in_"]) != n_features
    ):
        raise ModelFileError("the classes of a forest and of its trees disagree")
    estimators = []
    for t, state in enumerate(_build_trees(part, n_features, n_classes)):
        estimator = tree_cls(**spec["tree_params"], random_state=int(part["random_state"][t]))
        estimator.n_features_in_ = n_features
        estimator.n_outputs_ = 1
        estimator.classes_ = tree_classes.copy()
        estimator.n_classes_ = np.intp(n_classes)
        estimator.max_features_ = int(tree_fitted["max_features_"])
        estimator.tree_ = state
        estimators.append(estimator)
    forest = cls(**spec["params"])
    forest.n_features_in_ = n_features
    forest.n_outputs_ = 1
    forest.classes_ = classes
    forest.n_classes_ = n_classes
    for name in ("_n_samples", "_n_samples_bootstrap"):
        if name in fitted:
            setattr(forest, name, None if fitted[name] is None else int(fitted[name]))
    forest.estimator_ = forest.estimator
    forest.estimators_ = estimators
    return forest


def _build_trees(part: dict, n_features: int, n_classes: int) -> list:
    """The ``Tree`` objects of one checked part (:func:`_forest_parts`), in the installed
    scikit-learn's layout; the statistics not stored are NaN or 0."""
    split = part["split"]
    nodes = np.zeros(len(split), dtype=NODE_DTYPE)  # Tree.__setstate__ copies its slices
    nodes["left_child"] = part["left"]
    nodes["right_child"] = part["right"]
    n_nodes, inner = len(split), np.flatnonzero(split)
    for field, stored, fill in (
        ("feature", "feature", TREE_UNDEFINED),
        ("threshold", "threshold", float(TREE_UNDEFINED)),
        ("missing_go_to_left", "missing_left", 0),
    ):
        full = np.full(n_nodes, fill, dtype=nodes.dtype[field])
        full[inner] = part[stored]  # a contiguous scatter, then one strided copy
        nodes[field] = full
    nodes["impurity"] = np.nan
    nodes["n_node_samples"] = 0
    nodes["weighted_n_node_samples"] = np.nan
    values = np.full((n_nodes, n_classes), np.nan)
    values[np.flatnonzero(~split)] = part["values"]
    values = values.reshape(n_nodes, 1, n_classes)
    n_classes_array = np.array([n_classes], dtype=np.intp)
    trees = []
    for t, (start, stop) in enumerate(zip(part["offsets"][:-1], part["offsets"][1:], strict=True)):
        start, stop = int(start), int(stop)
        tree = Tree(n_features, n_classes_array, 1)
        tree.__setstate__(
            {
                "max_depth": int(part["max_depth"][t]),
                "node_count": stop - start,
                "nodes": nodes[start:stop],
                "values": values[start:stop],
            }
        )
        trees.append(tree)
    return trees
