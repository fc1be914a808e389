"""A fitted :class:`TripletPrior` as a JSON header and named arrays, and back.

The file itself is :func:`medseg.io.save_arrays`'s NPZ, as for every fitted part; this
module only maps the prior's attributes to the header and the arrays, and checks everything
it reads (shapes, finiteness, index ranges, valid mixtures), since a model file is
untrusted input.
"""

from __future__ import annotations

import numpy as np

from medseg.errors import ModelFileError
from medseg.io import check_format
from medseg.shape._invariants import INVARIANTS

__all__ = ["prior_state", "prior_from_state"]

_ARRAYS = ("mean_shape_", "cliques_", "weights_", "means_", "precisions_cholesky_",
           "n_components_")  # fmt: skip
_PARAMS = ("density", "invariant", "alpha", "max_components", "reg_covar", "n_neighbors",
           "max_cliques")  # fmt: skip


def prior_state(prior) -> tuple[dict, dict[str, np.ndarray]]:
    """``(header, arrays)`` of a fitted prior: JSON-able dict and named numpy arrays.

    Lets a composite model embed the prior in its own file.
    """
    params = {name: getattr(prior, name) for name in _PARAMS}
    params["cliques"] = prior.cliques if isinstance(prior.cliques, str) else "explicit"
    rs = prior.random_state
    params["random_state"] = int(rs) if isinstance(rs, (int, np.integer)) else None
    header = {
        "format": prior.FORMAT,
        "format_version": prior.FORMAT_VERSION,
        "params": params,
        "n_landmarks": int(prior.n_landmarks_),
        "n_training_shapes": int(prior.n_training_shapes_),
    }
    arrays = {name.rstrip("_"): np.asarray(getattr(prior, name)) for name in _ARRAYS}
    return header, arrays


def prior_from_state(cls, header: dict, arrays: dict, *, source: str = "the model"):
    """Rebuild a prior from :func:`prior_state` output; ``ModelFileError`` on any mismatch."""
    check_format(header, format=cls.FORMAT, version=cls.FORMAT_VERSION, source=source)
    try:
        params = dict(header["params"])
        n = int(header["n_landmarks"])
        get = {name: np.asarray(arrays[name.rstrip("_")]) for name in _ARRAYS}
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelFileError(f"{source} is incomplete or corrupt: missing {exc}") from None
    c = len(get["cliques_"])
    k = get["weights_"].shape[-1] if get["weights_"].ndim == 2 else -1
    dim = get["means_"].shape[-1] if get["means_"].ndim == 3 else -1
    if dim not in (2, 3):
        raise ModelFileError(f"{source} is corrupt: invariants of dimension {dim}, not 2 or 3")
    expected = {
        "mean_shape_": (n, 3),
        "cliques_": (c, 3),
        "weights_": (c, k),
        "means_": (c, k, dim),
        "precisions_cholesky_": (c, k, dim, dim),
        "n_components_": (c,),
    }
    for name, shape in expected.items():
        if get[name].shape != shape or not np.all(np.isfinite(get[name])):
            raise ModelFileError(
                f"{source} is corrupt: array {name.rstrip('_')!r} has shape {get[name].shape} "
                f"(expected {shape}) or non-finite values"
            )
    cl = get["cliques_"]
    pc = get["precisions_cholesky_"]
    w = get["weights_"]
    if (
        c == 0
        or cl.min() < 0
        or cl.max() >= n
        or not np.all(np.diagonal(pc, axis1=-2, axis2=-1) > 0)
        or not np.all(w >= 0)
        or not np.allclose(w.sum(axis=1), 1.0)
    ):
        raise ModelFileError(f"{source} is corrupt: clique indices or precisions are invalid")
    expected_dim = INVARIANTS[params["invariant"]](1.0, 1.0, 1.0).shape[-1]
    if dim != expected_dim:
        raise ModelFileError(
            f"{source} is corrupt: {dim}-D densities for the {expected_dim}-D invariant "
            f"{params['invariant']!r}"
        )
    cliques_param = params.pop("cliques")
    params.pop("random_state", None)
    prior = cls(
        cliques=cl.astype(np.int64) if cliques_param == "explicit" else cliques_param, **params
    )
    prior.n_landmarks_ = n
    prior.n_training_shapes_ = int(header.get("n_training_shapes", 0))
    for name in _ARRAYS:
        setattr(prior, name, get[name].astype(np.int64 if name in ("cliques_", "n_components_")
                                              else float))  # fmt: skip
    return prior
