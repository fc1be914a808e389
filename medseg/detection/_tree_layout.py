"""Whether the installed scikit-learn's trees can be rebuilt from arrays.

The stored forests (:mod:`medseg.detection._forest_arrays`) and the boosting's trees
(:mod:`medseg.detection._boosting`) both give ``sklearn.tree._tree.Tree`` its state through
``Tree.__setstate__``, as unpickling does: the one scikit-learn internal they rely on. This
module checks it (the state's keys, the node fields, and a probe tree that must predict as
expected) so that a future scikit-learn that changes it gives a clear error, not trees that
predict wrongly.
"""

from __future__ import annotations

import functools

import numpy as np
import sklearn
from sklearn.tree._tree import NODE_DTYPE, TREE_LEAF, TREE_UNDEFINED, Tree

from medseg.errors import ModelFileError

__all__ = ["NODE_FIELDS", "TREE_STATE_KEYS", "check_tree_layout", "layout_problem"]

#: the fields of scikit-learn's tree nodes (``NODE_DTYPE``) this format knows how to fill
NODE_FIELDS = (
    "left_child",
    "right_child",
    "feature",
    "threshold",
    "impurity",
    "n_node_samples",
    "weighted_n_node_samples",
    "missing_go_to_left",
)
#: the keys of ``Tree.__getstate__`` / ``__setstate__``
TREE_STATE_KEYS = ("max_depth", "node_count", "nodes", "values")


@functools.cache
def layout_problem() -> str | None:
    """Why the installed scikit-learn's trees cannot be rebuilt from arrays, or None."""
    if NODE_DTYPE.names is None or set(NODE_DTYPE.names) != set(NODE_FIELDS):
        return f"its tree nodes have the fields {NODE_DTYPE.names}, expected {NODE_FIELDS}"
    probe = Tree(1, np.array([2], dtype=np.intp), 1)
    if set(probe.__getstate__()) != set(TREE_STATE_KEYS):
        return f"its tree state has the keys {sorted(probe.__getstate__())}"
    # a stump: x <= 0.5 goes left (class 0), NaN goes right (class 1)
    nodes = np.zeros(3, dtype=NODE_DTYPE)
    nodes["left_child"] = [1, TREE_LEAF, TREE_LEAF]
    nodes["right_child"] = [2, TREE_LEAF, TREE_LEAF]
    nodes["feature"] = [0, TREE_UNDEFINED, TREE_UNDEFINED]
    nodes["threshold"] = [0.5, TREE_UNDEFINED, TREE_UNDEFINED]
    values = np.array([[[np.nan, np.nan]], [[1.0, 0.0]], [[0.0, 1.0]]])
    try:
        probe.__setstate__({"max_depth": 1, "node_count": 3, "nodes": nodes, "values": values})
        X = np.array([[0.25], [0.5], [0.75], [np.nan]], dtype=np.float32)
        got = np.asarray(probe.predict(X)).reshape(len(X), 2)
        back = probe.__getstate__()["nodes"]
    except Exception as exc:  # any failure of the probe means the layout changed
        return f"a probe tree could not be rebuilt ({type(exc).__name__}: {exc})"
    if not np.array_equal(got, [[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0]]):
        return "a probe tree rebuilt from its nodes predicts differently"
    if any(not np.array_equal(back[f], nodes[f]) for f in ("left_child", "feature", "threshold")):
        return "a probe tree does not keep the nodes it is given"
    return None


def check_tree_layout(saved_with: str | None = None, source: str = "the forests") -> None:
    """Refuse to rebuild trees if the installed scikit-learn stores them differently.

    ``saved_with`` is the scikit-learn version the file was written with, ``source`` the
    file, both for the message.

    Raises
    ------
    ModelFileError
        The installed scikit-learn's ``Tree`` state or node fields are not those this
        format fills (a newer scikit-learn changed them): say which, and what to do.
    """
    problem = layout_problem()
    if problem:
        where = f" (written with scikit-learn {saved_with})" if saved_with else ""
        raise ModelFileError(
            f"{source}{where}: its forests cannot be rebuilt with the installed scikit-learn "
            f"{sklearn.__version__}, {problem}; install the scikit-learn the model was saved "
            "with, or re-save the detector in format version 1 (skops) with it"
        )
