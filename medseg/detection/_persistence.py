"""Saving and loading landmark detectors: the forests as arrays, JSON for everything else.

A saved detector is a folder::

    detector.json    format name and version, constructor parameters, feature settings,
                     fitted metadata (number of landmarks, feature names, ...)
    forests.npz      version 2: the landmark forests, then the cascade's region forest if
                     there is one, as plain arrays (:mod:`medseg.detection._forest_arrays`)
    forests.skops    version 1: the same forests in skops format (no pickle, a list of
                     trusted types); still read, and written with ``format_version=1``
    stage1/          with auto-context: the first stage, a saved detector itself

Version 2 gives the same probabilities bit for bit; for a detector of 77 forests of 60 trees
it loads some 20 times faster than skops (about 1-2 s instead of 25-40 s) from a file some 25
times smaller (24 MB instead of 629 MB). A forest it cannot store exactly (not a plain
random / extra-trees classifier with JSON-able parameters, or an installed scikit-learn of
unknown tree layout) is written in version 1 instead, with a warning.

The folder is written next to its destination and renamed into place, so a failed save never
leaves a half-written detector.

This module does not import :class:`~medseg.detection.LandmarkDetector`: the class imports
it, and :func:`read_detector` is given the class to build. :func:`load_detector`, the public
reader, is defined next to the class.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import skops.io as sio
from sklearn.ensemble import ExtraTreesClassifier, RandomForestClassifier

from medseg.detection._features import FeatureSettings
from medseg.detection._forest_arrays import (
    UnsupportedForest,
    check_forests,
    load_forests,
    save_forests,
)
from medseg.detection._prediction import forest_feature_names
from medseg.errors import (
    InputFileError,
    MedsegError,
    ModelFileError,
    NotFittedError,
    ParameterError,
)
from medseg.io import atomic_folder
from medseg.io._archive import check_archive

__all__ = ["save_detector", "read_detector", "FORMAT_NAME", "FORMAT_VERSION", "WRITE_VERSION"]

FORMAT_NAME = "medseg.detection.LandmarkDetector"
FORMAT_VERSION = 2  # the newest version read
#: the version ``save`` writes by default
WRITE_VERSION = 2
_META = "detector.json"
_FORESTS = "forests.skops"  # version 1
_ARRAYS = "forests.npz"  # version 2
_STAGE1 = "stage1"
# Types a detector's skops file may hold beyond those skops trusts by default (scikit-learn
# estimators without callables, numpy arrays and dtypes, builtin containers): an explicit
# list, never ``trusted=True``. Any other type means a tampered or foreign file.
TRUSTED_TYPES = ("sklearn.tree._tree.Tree",)
_FOREST_TYPES = (RandomForestClassifier, ExtraTreesClassifier)


def save_detector(detector, path, *, format_version: int | None = None) -> Path:
    """Write a fitted :class:`LandmarkDetector` to the folder ``path``.

    Parameters
    ----------
    detector : LandmarkDetector
        Fitted.
    path : str or Path
        Folder to create. An existing folder is replaced only if it holds a saved detector.
    format_version : {2, 1}, optional
        2: the forests as arrays (``forests.npz``); 1: skops (``forests.skops``), which
        medseg releases before format 2 read. Default :data:`WRITE_VERSION`. Stage 1 of an
        auto-context detector is written in the same version.

    Returns
    -------
    path : Path
    """
    if not hasattr(detector, "forests_"):
        raise NotFittedError("save: the detector is not fitted; call fit() before save()")
    format_version = WRITE_VERSION if format_version is None else format_version
    if format_version not in (1, 2):
        raise ParameterError(f"save: `format_version` must be 1 or 2, got {format_version!r}")
    path = Path(path)
    if path.exists() and not (path.is_dir() and (path / _META).is_file()):
        raise InputFileError(
            f"save: {path} exists and is not a saved detector; choose another path so "
            "nothing is overwritten"
        )
    params = detector.get_params(deep=False)
    params["features"] = params["features"].to_dict()
    params["random_state"] = (
        params["random_state"] if isinstance(params["random_state"], int | None) else None
    )
    meta = {
        "format": FORMAT_NAME,
        "version": format_version,
        "params": params,
        "fitted": {
            "n_landmarks": detector.n_landmarks_,
            "n_features": detector.n_features_,
            "feature_names": detector.feature_names_,
            "n_dims": detector.n_dims_,
            "n_samples": np.asarray(detector.n_samples_).tolist(),
            "fit_time_s": float(detector.fit_time_),
        },
    }
    stage1 = getattr(detector, "stage1_", None)
    if stage1 is not None:
        meta["fitted"]["context_groups"] = np.asarray(detector.context_groups_).tolist()
        meta["fitted"]["context_radii_mm"] = list(detector.context_radii_mm_)
    region = detector.region_forest_
    with atomic_folder(path) as tmp:
        if format_version == 2:
            try:
                forests = list(detector.forests_) + [region] * (region is not None)
                save_forests(tmp / _ARRAYS, forests)
                meta["fitted"]["region_forest"] = region is not None
            except UnsupportedForest as exc:
                warnings.warn(
                    f"save: the forests cannot be stored as arrays ({exc}); writing them in "
                    "skops (detector format version 1), which loads much more slowly",
                    stacklevel=2,
                )
                meta["version"] = 1
        if meta["version"] == 1:
            payload = {"forests": list(detector.forests_), "region": region}
            sio.dump(payload, tmp / _FORESTS)
        (tmp / _META).write_text(json.dumps(meta, indent=2, sort_keys=True), encoding="utf-8")
        if stage1 is not None:
            save_detector(stage1, tmp / _STAGE1, format_version=format_version)
    return path


def read_detector(cls, path):
    """Read a detector written by :func:`save_detector`, as an instance of ``cls``.

    Parameters
    ----------
    cls : type
        :class:`~medseg.detection.LandmarkDetector` (or a subclass): built from the saved
        constructor parameters, then given the fitted attributes.
    path : str or Path
        The folder.

    Raises
    ------
    InputFileError
        If ``path`` is not a folder holding ``detector.json`` and its forests file
        (``forests.npz`` in version 2, ``forests.skops`` in version 1).
    ModelFileError
        If the files are corrupt, of another format or version, or hold unexpected types.
    """
    path = Path(path)
    if not (path / _META).is_file():
        raise InputFileError(
            f"load: {path} is not a saved detector folder (needs {_META} and {_ARRAYS} or "
            f"{_FORESTS}); give the folder written by LandmarkDetector.save"
        )
    try:
        meta = json.loads((path / _META).read_text(encoding="utf-8"))
        if meta.get("format") != FORMAT_NAME:
            raise ModelFileError(f"load: {path / _META} is not a {FORMAT_NAME} file")
        version = int(meta.get("version", 1))
        if version > FORMAT_VERSION:
            raise ModelFileError(
                f"load: {path} was written in format version {meta['version']}, newer than "
                f"this medseg reads ({FORMAT_VERSION}); upgrade medseg"
            )
        if version < 1:
            raise ModelFileError(f"load: {path / _META} has an invalid format version {version}")
        params = dict(meta["params"])
        params.setdefault("auto_context", False)  # saved before auto-context existed
        params["features"] = FeatureSettings.from_dict(params["features"])
        for name in ("augment_scales", "augment_scale_range"):  # JSON has no tuples
            if isinstance(params.get(name), list):
                params[name] = tuple(params[name])
        fitted = meta["fitted"]
        detector = cls(**params)
    except ModelFileError:
        raise
    except (ValueError, KeyError, TypeError, AttributeError, MedsegError) as exc:
        raise ModelFileError(f"load: {path / _META} is corrupt or incomplete ({exc})") from None
    forests_file = path / (_FORESTS if version == 1 else _ARRAYS)
    if not forests_file.is_file():
        raise InputFileError(
            f"load: {path} is not a saved detector folder (a version-{version} detector needs "
            f"{forests_file.name}); give the folder written by LandmarkDetector.save"
        )
    try:
        detector.n_landmarks_ = int(fitted["n_landmarks"])
        detector.n_features_ = int(fitted["n_features"])
        detector.feature_names_ = list(fitted["feature_names"])
        detector.n_dims_ = int(fitted["n_dims"])
        detector.n_samples_ = np.asarray(fitted["n_samples"], dtype=int)
        detector.fit_time_ = float(fitted["fit_time_s"])
        has_region = fitted.get("region_forest") if version >= 2 else None
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ModelFileError(f"load: {path / _META} is corrupt or incomplete ({exc})") from None
    if version == 1:
        forests, region = _read_skops(path)
    else:
        forests = load_forests(forests_file)
        if not isinstance(has_region, bool) or len(forests) < has_region:
            raise ModelFileError(
                f"load: {path / _META} does not say whether there is a region forest"
            )
        region = forests.pop() if has_region else None
    detector.forests_ = list(forests)
    detector.region_forest_ = region
    detector.stage1_ = detector.context_groups_ = detector.context_radii_mm_ = None
    if detector.auto_context:
        if not (path / _STAGE1).is_dir():
            raise ModelFileError(
                f"load: {path} has no {_STAGE1}/ folder, which an auto-context detector needs; "
                "the folder was modified after saving"
            )
        detector.stage1_ = read_detector(cls, path / _STAGE1)
        try:
            groups = np.asarray(fitted["context_groups"], dtype=int)
            radii = tuple(float(r) for r in fitted["context_radii_mm"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"load: {path / _META} is corrupt ({exc})") from None
        if groups.shape != (detector.n_landmarks_,) or groups.min() < 0 or not radii:
            raise ModelFileError(f"load: {path / _META} has invalid context groups or radii")
        if detector.stage1_.n_landmarks_ != detector.n_landmarks_:
            raise ModelFileError(f"load: {path}: stage 1 and stage 2 disagree on the landmarks")
        detector.context_groups_, detector.context_radii_mm_ = groups, radii
    expected = len(detector.forests_) == (
        detector.n_landmarks_ if detector.mode == "per_landmark" else 1
    )
    widths = {int(f.n_features_in_) for f in detector.forests_}
    if (
        not expected
        or widths - {detector.n_features_}
        or detector.feature_names_ != forest_feature_names(detector)
    ):
        raise ModelFileError(
            f"load: {path} is inconsistent (forest count or feature names do not match the "
            "settings); the folder was modified after saving"
        )
    return detector


def _read_skops(path: Path) -> tuple[list, object]:
    """The landmark forests and the region forest (or None) of a version-1 folder."""
    check_archive(path / _FORESTS)  # size and .npy headers, before skops unpacks anything
    try:
        untrusted = sio.get_untrusted_types(file=path / _FORESTS)
    except Exception as exc:  # skops raises various errors on a corrupt zip
        raise ModelFileError(f"load: {path / _FORESTS} is corrupt ({exc})") from None
    foreign = sorted(set(untrusted) - set(TRUSTED_TYPES))
    if foreign:
        raise ModelFileError(
            f"load: {path / _FORESTS} holds unexpected types {foreign}; refusing to load a "
            "file that may have been tampered with"
        )
    try:
        payload = sio.load(path / _FORESTS, trusted=list(TRUSTED_TYPES))
        forests, region = list(payload["forests"]), payload["region"]
    except Exception as exc:
        raise ModelFileError(f"load: {path / _FORESTS} is corrupt ({exc})") from None
    if not all(isinstance(f, _FOREST_TYPES) for f in forests + [region] if f is not None):
        raise ModelFileError(
            f"load: {path / _FORESTS} holds objects that are not scikit-learn forests; "
            "refusing to use it"
        )
    check_forests(forests + [region] * (region is not None), path / _FORESTS)
    return forests, region
