"""Model folders on disk: JSON + NPZ + skops, a format version, checksums, no pickle.

Layout of a model folder::

    model.json        format version, medseg version, parameters, training summary,
                      and the SHA-256 of every other file
    template.npz      template mask (with its geometry), landmarks, surface, training landmarks
    detector/         written by LandmarkDetector.save (JSON + NPZ arrays; skops in
                      detector format 1)
    prior.npz         written by TripletPrior.save (NPZ with a JSON header)
    orientation.npz   written by OrientationPrior.save; since version 2
    shape_model.npz   written by ActiveShapeModel.save (the model refining the landmarks);
                      since version 3
    frame.npz         written by ShapeFrame.save (the shape's own frame); since version 4
    boundary/         written by BoundaryStage.save (stage.npz, classifier.npz and with
                      auto-context context.npz: the regional stage); since version 5 (a
                      model trained without the stage is written as version 4)
    appearance.npz    written by FrameAppearance.save (the training images' mean in the
                      shape's frame, for the appearance check); since version 7

The folder is built in a staging sibling and swapped into place (``atomic_folder``), so a
failed save leaves no half-written model. Loading verifies the format version and every checksum
before anything is deserialised.

A model folder is untrusted input: nothing on the load path uses pickle (``allow_pickle=False``
on every ``np.load``; skops with an explicit list of trusted types), and every archive
(``template.npz``, ``prior.npz``, ``orientation.npz``, ``shape_model.npz``,
``detector/**/forests.npz`` or ``forests.skops``, ``boundary/*.npz``,
``appearance.npz``) is checked
from its zip directory and ``.npy`` headers before it is unpacked
(:func:`medseg.io._archive.check_archive`): an oversized, forged or malformed archive is refused
with a :class:`ModelFileError`.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from medseg._version import __version__
from medseg.detection import LandmarkDetector
from medseg.errors import InputFileError, ModelFileError
from medseg.frame import ShapeFrame
from medseg.io import atomic_folder, check_format, load_arrays, save_arrays
from medseg.io._archive import MAX_UNPACKED_BYTES, check_archive
from medseg.segmenter._appearance import FrameAppearance
from medseg.segmenter._boundary import BoundaryStage
from medseg.shape import ActiveShapeModel, OrientationPrior, TripletPrior

FORMAT = "medseg-shape-prior-segmenter"
FORMAT_VERSION = 7
#: versions this medseg reads: 1 lacks the handedness term (``orientation.npz``), 1 and 2
#: the landmark refinement (``shape_model.npz`` and the ``refine_levels`` parameter), 1-3
#: the shape's frame (``frame.npz``, ``frame_passes``), 1-4 the regional stage
#: (``boundary/``, ``boundary``), 1-5 the hypotheses' stopping rule
#: (``hypothesis_quantile``; their shape model has no training costs), 1-6 the appearance
#: check (``appearance.npz``, ``appearance_check``)
_READABLE_VERSIONS = (1, 2, 3, 4, 5, 6, 7)
#: format version that introduced an optional file or parameter
_SINCE = {
    "orientation.npz": 2,
    "shape_model.npz": 3,
    "refine_levels": 3,
    "n_hypotheses": 3,
    # new in 6, but written with the shape model it applies to, so that a model without the
    # regional stage (saved as version 4) keeps it
    "hypothesis_quantile": 3,
    "frame.npz": 4,
    "frame_passes": 4,
    "augment_poses": 4,
    "boundary": 5,
    "boundary/stage.npz": 5,
    "boundary/classifier.npz": 5,
    "appearance.npz": 7,
    "appearance_check": 7,
}
_PARAMS = (
    "n_landmarks",
    "labels",
    "n_candidates",
    "cliques",
    "density",
    "invariant",
    "alpha",
    "orientation_weight",
    "orientation_sigma_mm",
    "refine_levels",
    "n_hypotheses",
    "hypothesis_quantile",
    "frame_passes",
    "appearance_check",
    "boundary",
    "landmark_noise_mm",
    "n_noise_copies",
    "n_estimators",
    "augment_poses",
    "smoothing",
    "max_iter",
    "mrf_method",
    "n_jobs",
)
MAX_MODEL_BYTES = 2 * 1024**3
_ARCHIVES = ("template.npz", "prior.npz", "orientation.npz", "shape_model.npz", "frame.npz",
             "boundary/stage.npz", "boundary/classifier.npz", "appearance.npz")  # fmt: skip
#: the detector's forests: arrays (detector format 2) or skops (format 1), at any depth
#: (stage1/ of an auto-context detector holds its own)
_DETECTOR_ARCHIVES = ("forests.npz", "forests.skops")
_TEMPLATE_HEADER_CHECK = {"format": "medseg.segmenter.template", "version": 1}
_TEMPLATE_HEADER = {"format": "medseg.segmenter.template", "format_version": 1}
_TEMPLATE_ARRAYS = ("mask", "spacing", "origin", "direction", "landmarks", "vertices", "faces",
                    "training_landmarks")  # fmt: skip


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file() and p.name != "model.json")


def save_model(model, path: Path) -> Path:
    path = Path(path)
    if path.exists() and not (path / "model.json").is_file():
        raise InputFileError(
            f"{path} exists and is not a medseg model folder; choose another output path"
        )
    with atomic_folder(path) as tmp:
        mask = model.template_mask_
        vertices, faces = model.template_surface_
        template = {
            "mask": sitk.GetArrayFromImage(mask).astype(np.uint8),
            "spacing": np.asarray(mask.GetSpacing()),
            "origin": np.asarray(mask.GetOrigin()),
            "direction": np.asarray(mask.GetDirection()),
            "landmarks": np.asarray(model.template_landmarks_),
            "vertices": np.asarray(vertices, dtype=float),
            "faces": np.asarray(faces, dtype=np.int64),
            "training_landmarks": np.asarray(model.landmarks_),
        }
        save_arrays(tmp / "template.npz", template, header=_TEMPLATE_HEADER)
        model.detector_.save(tmp / "detector")
        model.prior_.save(tmp / "prior.npz")
        # a model loaded from an older version lacks its newer parts and keeps its version
        version = 1
        if model.orientation_ is not None:
            model.orientation_.save(tmp / "orientation.npz")
            version = 2
            if model.shape_model_ is not None:
                model.shape_model_.save(tmp / "shape_model.npz")
                version = 3
                if getattr(model, "frame_", None) is not None:
                    model.frame_.save(tmp / "frame.npz")
                    version = 4  # a model without the regional stage is one of version 4
                    if getattr(model, "boundary_", None) is not None:
                        model.boundary_.save(tmp / "boundary")
                        version = 5
                        if model.shape_model_.training_costs_ is not None:
                            version = 6
                            if getattr(model, "appearance_", None) is not None:
                                model.appearance_.save(tmp / "appearance.npz")
                                version = 7
        meta = {
            "format": FORMAT,
            "format_version": version,
            "medseg_version": __version__,
            "params": {
                name: _jsonable(getattr(model, name))
                for name in _PARAMS
                if _SINCE.get(name, 1) <= version
            },
            "cases": list(model.cases_),
            "rejected": dict(model.rejected_),
            "checksums": {str(p.relative_to(tmp)): _sha256(p) for p in _files(tmp)},
        }
        (tmp / "model.json").write_text(
            json.dumps(meta, indent=2, sort_keys=True), encoding="utf-8"
        )
    return path


def load_model(cls, path: Path):
    path = Path(path)
    meta_path = path / "model.json"
    if not meta_path.is_file():
        raise ModelFileError(
            f"{path} is not a medseg model folder (no model.json); train one with medseg-train"
        )
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelFileError(f"{meta_path} is not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ModelFileError(f"{meta_path} does not describe a medseg segmentation model")
    version = meta.get("format_version")
    if version not in _READABLE_VERSIONS:
        raise ModelFileError(
            f"{path} has model format version {version!r} (written by medseg "
            f"{meta.get('medseg_version', '?')}); this medseg {__version__} reads "
            f"versions {', '.join(map(str, _READABLE_VERSIONS))}: retrain the model or install "
            "the matching medseg"
        )
    _verify_checksums(path, meta.get("checksums"))
    _check_archives(path, version)

    params = meta.get("params")
    if not isinstance(params, dict) or not set(params) <= set(_PARAMS):
        unknown = sorted(set(params) - set(_PARAMS)) if isinstance(params, dict) else params
        raise ModelFileError(f"{meta_path}: unknown or malformed model parameters {unknown!r}")
    if isinstance(params.get("labels"), list):
        params["labels"] = tuple(params["labels"])  # JSON has no tuples
    model = cls(**params)
    if version < _SINCE["refine_levels"]:
        model.refine_levels = 0  # saved before the refinement existed: the MRF's landmarks
    if "augment_poses" not in params:
        model.augment_poses = 0  # trained before posed copies existed: its detectors saw none
    template = path / "template.npz"
    header, npz = load_arrays(template, what="model template")
    check_format(header, **_TEMPLATE_HEADER_CHECK, source=str(template), missing_ok=True)
    missing = [name for name in _TEMPLATE_ARRAYS if name not in npz]
    if missing:
        raise ModelFileError(f"{template} lacks the arrays {missing}")
    try:
        mask = sitk.GetImageFromArray(npz["mask"])
        mask.SetSpacing(npz["spacing"].tolist())
        mask.SetOrigin(npz["origin"].tolist())
        mask.SetDirection(npz["direction"].tolist())
    except (ValueError, TypeError, RuntimeError) as exc:
        raise ModelFileError(f"{template} is corrupt ({exc})") from None
    model.template_mask_ = mask
    model.template_landmarks_ = npz["landmarks"]
    model.template_surface_ = (npz["vertices"], npz["faces"])
    model.landmarks_ = npz["training_landmarks"]
    model.detector_ = LandmarkDetector.load(path / "detector")
    model.prior_ = TripletPrior.load(path / "prior.npz")
    model.orientation_ = _load_part(path, "orientation.npz", version, OrientationPrior)
    if model.orientation_ is not None and not np.array_equal(
        model.orientation_.cliques_, model.prior_.cliques_
    ):
        raise ModelFileError(f"{path / 'orientation.npz'} does not match the cliques of prior.npz")
    model.shape_model_ = _load_part(path, "shape_model.npz", version, ActiveShapeModel)
    model.frame_ = _load_part(path, "frame.npz", version, ShapeFrame)
    model.appearance_ = _load_part(path, "appearance.npz", version, FrameAppearance)
    model.boundary_ = None
    if version >= _SINCE["boundary"]:
        model.boundary_ = BoundaryStage.load(path / "boundary")
        template_values = tuple(int(v) for v in np.unique(npz["mask"]) if v)
        if model.boundary_.values_ != template_values:
            raise ModelFileError(
                f"{path / 'boundary'} labels {model.boundary_.values_} do not match the "
                f"template's {template_values}"
            )
    else:
        model.boundary = False  # no regional stage: the shape-only label map
    if model.frame_ is not None and model.frame_.reference.shape != np.shape(model.landmarks_)[1:]:
        raise ModelFileError(f"{path / 'frame.npz'} does not match the landmarks of template.npz")
    if model.appearance_ is not None and not model.appearance_.fits(model.frame_):
        raise ModelFileError(f"{path / 'appearance.npz'} does not match the grid of frame.npz")
    if model.shape_model_ is not None and (
        model.shape_model_.mean_shape_.shape != np.shape(model.landmarks_)[1:]
    ):
        raise ModelFileError(
            f"{path / 'shape_model.npz'} does not match the landmarks of template.npz"
        )
    model.cases_ = list(meta.get("cases", []))
    model.rejected_ = dict(meta.get("rejected", {}))
    return model


def _load_part(path: Path, name: str, version: int, cls):
    """``cls.load`` of the part file ``name``, or None when ``version`` predates it."""
    if version < _SINCE[name]:
        return None
    file = path / name
    if not file.is_file():
        raise ModelFileError(f"{file} is missing; the model is incomplete")
    return cls.load(file)


def _check_archives(path: Path, version: int) -> None:
    """Refuse oversized, forged or malformed archives before anything is unpacked."""
    total = 0
    for name in _ARCHIVES:
        if _SINCE.get(name, 1) > version:
            continue
        if not (path / name).is_file():
            raise ModelFileError(f"{path} is missing {name}; the model folder is incomplete")
        total += check_archive(path / name)
    forests = sorted(p for p in (path / "detector").rglob("forests.*")
                     if p.name in _DETECTOR_ARCHIVES and p.is_file())  # fmt: skip
    if (
        not (path / "detector" / "forests.npz").is_file()
        and not (path / "detector" / "forests.skops").is_file()
    ):
        raise ModelFileError(
            f"{path} is missing detector/forests.npz; the model folder is incomplete"
        )
    context = path / "boundary" / "context.npz"  # with auto-context (BoundaryStage)
    for file in forests + ([context] if version >= 5 and context.is_file() else []):
        total += check_archive(file)
    if total > MAX_UNPACKED_BYTES:
        raise ModelFileError(
            f"{path}: its archives declare {total / 1e9:.1f} GB of uncompressed content, above "
            f"the limit of {MAX_UNPACKED_BYTES / 1e9:.1f} GB; refusing to load it"
        )


def _verify_checksums(path: Path, checksums) -> None:
    if not isinstance(checksums, dict) or not checksums:
        raise ModelFileError(f"{path}/model.json lists no checksums; the model is incomplete")
    listed = set(checksums)
    present = {str(p.relative_to(path)) for p in _files(path)}
    if listed - present:
        raise ModelFileError(
            f"{path} is missing {sorted(listed - present)}; the model folder is incomplete"
        )
    total = sum((path / name).stat().st_size for name in listed)
    if total > MAX_MODEL_BYTES:
        raise ModelFileError(f"{path} holds {total / 1e9:.1f} GB; refusing to load it")
    for name in sorted(listed):
        if _sha256(path / name) != checksums[name]:
            raise ModelFileError(
                f"{path / name} does not match its checksum in model.json: the file was "
                "changed or damaged after saving; do not use it"
            )


def _jsonable(value):
    if isinstance(value, tuple):
        return list(value)
    if isinstance(value, np.generic):
        return value.item()
    return value
