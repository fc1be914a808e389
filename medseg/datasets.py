"""Cohorts: discovery from MSD / nnU-Net folders and CSV manifests, and the synthetic phantom.

A :class:`Cohort` is a sequence of :class:`Case` objects (image, label map, optional
landmarks) that knows each case's *subject*: cases of one person share a subject key, so
cross-validation can split by subject (``GroupKFold(groups=cohort.subjects)``).

* :func:`load_cohort` reads an MSD / nnU-Net folder (``dataset.json``, ``imagesTr/``,
  ``labelsTr/``, optional ``landmarksTr/`` and ``subjects.csv``) or a CSV manifest.
* :func:`make_phantom_cohort` generates the package's embedded synthetic cohort.
* :func:`write_cohort` writes any cohort in the MSD layout, so every CLI can run on it.
"""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from sklearn.utils import check_random_state

from medseg._phantom import make_phantom_case, phantom_landmark_index
from medseg.errors import CohortError, InputFileError, LabelError, ParameterError
from medseg.io import (
    atomic_folder,
    read_image,
    read_label,
    read_landmarks,
    write_image,
    write_landmarks,
)

__all__ = [
    "Case",
    "Cohort",
    "load_cohort",
    "make_phantom_cohort",
    "write_cohort",
    "phantom_landmark_index",
]

_LANDMARK_SUFFIXES = (".mrk.json", ".fcsv", ".csv")
_MANIFEST_COLUMNS = {
    "image": "image",
    "label": "label",
    "subject": "subject",
    "subject_key": "subject",
    "landmarks": "landmarks",
    "case_id": "case_id",
    "case": "case_id",
}


# ----------------------------------------------------------------------------- data model


@dataclass
class Case:
    """One image with its label map, landmarks and subject.

    Parameters
    ----------
    case_id : str
        Unique name of the case within its cohort (file stem without channel suffix).
    subject : str
        Subject key; cases of one person share it.
    image : Path or sitk.Image
    label : Path, sitk.Image or None
        The raw label map, all labels.
    landmarks : Path, (N, 3) float array (mm, x, y, z) or None
        Ground-truth landmarks, or a landmark file (``.csv``, ``.fcsv``, ``.mrk.json``).
    meta : dict
        Anything else (phantom ground truth: ``surface_points``, ``landmark_index``,
        ``pose``, ...).
    """

    case_id: str
    subject: str
    image: Path | sitk.Image
    label: Path | sitk.Image | None = None
    landmarks: Path | np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def load_image(self) -> sitk.Image:
        """The image as a SimpleITK image (read from disk when a path)."""
        return read_image(self.image)

    def load_label(self) -> sitk.Image:
        """The raw label map (all labels), checked against the image's geometry.

        Raises
        ------
        LabelError
            The case has no label map.
        """
        if self.label is None:
            raise LabelError(f"case {self.case_id!r} has no label map")
        reference = self.image if isinstance(self.image, sitk.Image) else None
        if reference is None and isinstance(self.image, str | os.PathLike):
            reference = self.image
        return read_label(self.label, reference)

    def load_landmarks(self) -> np.ndarray | None:
        """Ground-truth landmarks, (N, 3) float array in mm (x, y, z), or None."""
        if self.landmarks is None:
            return None
        if isinstance(self.landmarks, np.ndarray):
            return np.asarray(self.landmarks, dtype=float)
        return read_landmarks(self.landmarks)


@dataclass
class Cohort:
    """A sequence of :class:`Case` with label names and subject grouping.

    Parameters
    ----------
    cases : list of Case
    labels : dict of str to int
        Label names to values (``{"background": 0, "target": 1}``).
    name : str
    root : Path or None
        Folder or manifest the cohort was read from; None when in memory.
    """

    cases: list[Case]
    labels: dict[str, int] = field(default_factory=dict)
    name: str = "cohort"
    root: Path | None = None

    def __len__(self) -> int:
        return len(self.cases)

    def __iter__(self) -> Iterator[Case]:
        return iter(self.cases)

    def __getitem__(self, item):
        """A case by position; a slice or an index array gives a sub-cohort."""
        if isinstance(item, int | np.integer):
            return self.cases[item]
        if isinstance(item, slice):
            cases = self.cases[item]
        else:
            index = np.asarray(item).ravel()
            if index.dtype == bool:
                if index.size != len(self.cases):
                    raise IndexError(f"boolean mask of {index.size} for {len(self.cases)} cases")
                index = np.flatnonzero(index)
            cases = [self.cases[int(i)] for i in index]
        return Cohort(cases=cases, labels=dict(self.labels), name=self.name, root=self.root)

    @property
    def subjects(self) -> np.ndarray:
        """(n_cases,) array of subject keys: the groups for ``GroupKFold``."""
        return np.asarray([c.subject for c in self.cases], dtype=object)

    @property
    def case_ids(self) -> list[str]:
        return [c.case_id for c in self.cases]

    def __repr__(self) -> str:
        n_subjects = len(set(self.subjects))
        return (
            f"Cohort(name={self.name!r}, {len(self)} cases, {n_subjects} subjects, "
            f"labels={self.labels}, root={str(self.root) if self.root else None!r})"
        )


# ----------------------------------------------------------------------------- discovery


def _labels_from_json(value, path: Path) -> dict[str, int]:
    """MSD ``{"0": "background"}`` or nnU-Net v2 ``{"background": 0}`` -> name -> int."""
    if not isinstance(value, dict) or not value:
        raise CohortError(f"{path}: 'labels' must be a non-empty object, got {value!r}")
    labels: dict[str, int] = {}
    for key, val in value.items():
        if isinstance(val, str) and str(key).lstrip("-").isdigit():  # MSD: int -> name
            labels[val] = int(key)
        elif isinstance(val, int | float) and not isinstance(val, bool) and float(val).is_integer():
            labels[str(key)] = int(val)  # nnU-Net v2: name -> int
        else:
            raise CohortError(
                f'{path}: label entry {key!r}: {val!r} is neither MSD form ("1": "name") '
                'nor nnU-Net v2 form ("name": 1); region-based labels are not supported'
            )
    return labels


def _strip_ending(name: str, ending: str) -> str | None:
    return name[: -len(ending)] if name.endswith(ending) else None


def _case_id_from_image(name: str, ending: str) -> tuple[str, str | None]:
    """Case id and channel (``"0000"``) of an image file name, channel None if absent."""
    stem = _strip_ending(name, ending) or name
    head, sep, channel = stem.rpartition("_")
    if sep and len(channel) == 4 and channel.isdigit():
        return head, channel
    return stem, None


def _visible_files(folder: Path, ending: str) -> list[Path]:
    return sorted(
        p
        for p in folder.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.name.endswith(ending)
    )


def _find_landmark_file(folder: Path, case_id: str) -> Path | None:
    if not folder.is_dir():
        return None
    for suffix in _LANDMARK_SUFFIXES:
        candidate = folder / f"{case_id}{suffix}"
        if candidate.is_file():
            return candidate
    return None


def _read_subjects(path: Path, case_ids: list[str]) -> dict[str, str]:
    """Case id -> subject key from a ``subjects.csv`` (columns case/case_id/image, subject_key)."""
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        columns = [c.strip() for c in (reader.fieldnames or [])]
        key_col = next((c for c in ("subject_key", "subject") if c in columns), None)
        id_col = next((c for c in ("case", "case_id", "image") if c in columns), None)
        if key_col is None or id_col is None:
            raise CohortError(
                f"{path}: needs a 'subject_key' column and a 'case' (or 'case_id' / 'image') "
                f"column, found {columns}"
            )
        mapping = {}
        for row in reader:
            raw = (row.get(id_col) or "").strip()
            if id_col == "image":
                raw = _case_id_from_image(Path(raw).name, ".nii.gz")[0]
            mapping[raw] = (row.get(key_col) or "").strip()
    missing = [c for c in case_ids if not mapping.get(c)]
    if missing:
        raise CohortError(
            f"{path}: no subject_key for {len(missing)} case(s) ({', '.join(missing[:5])}); "
            "give every case a subject or remove subjects.csv to treat each case as its own "
            "subject"
        )
    return {c: mapping[c] for c in case_ids}


def _load_msd(root: Path) -> Cohort:
    images_dir, labels_dir = root / "imagesTr", root / "labelsTr"
    for folder in (images_dir, labels_dir):
        if not folder.is_dir():
            raise CohortError(
                f"{root}: missing folder {folder.name}/; an MSD / nnU-Net cohort has "
                "dataset.json, imagesTr/ and labelsTr/"
            )
    spec_path = root / "dataset.json"
    spec: dict = {}
    if spec_path.is_file():
        try:
            spec = json.loads(spec_path.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise CohortError(f"{spec_path}: not valid JSON ({exc})") from None
        if not isinstance(spec, dict):
            raise CohortError(f"{spec_path}: expected a JSON object")
    labels = _labels_from_json(spec["labels"], spec_path) if "labels" in spec else {}
    ending = str(spec.get("file_ending", ".nii.gz"))

    pairs: list[tuple[str, Path, Path]] = []
    if isinstance(spec.get("training"), list) and spec["training"]:
        for k, entry in enumerate(spec["training"]):
            if not isinstance(entry, dict) or "image" not in entry or "label" not in entry:
                raise CohortError(
                    f"{spec_path}: training entry {k} must have 'image' and 'label', got {entry!r}"
                )
            image = (root / entry["image"]).resolve()
            label = (root / entry["label"]).resolve()
            case_id, channel = _case_id_from_image(image.name, ending)
            if not image.is_file() and channel is None:
                with_channel = image.with_name(f"{case_id}_0000{ending}")
                image = with_channel if with_channel.is_file() else image
            if not image.is_file():
                raise CohortError(f"{spec_path}: training entry {k}: image {image} does not exist")
            if not label.is_file():
                raise CohortError(
                    f"{spec_path}: training entry {k}: image {image.name} has no label "
                    f"({label} does not exist)"
                )
            pairs.append((case_id, image, label))
    else:
        label_files = {_strip_ending(p.name, ending): p for p in _visible_files(labels_dir, ending)}
        seen: set[str] = set()
        for image in _visible_files(images_dir, ending):
            case_id, channel = _case_id_from_image(image.name, ending)
            if channel not in (None, "0000"):
                continue  # further channels of a multi-channel case: the first one is used
            if case_id in seen:
                raise CohortError(f"{images_dir}: more than one image for case {case_id!r}")
            seen.add(case_id)
            if case_id not in label_files:
                raise CohortError(
                    f"{image}: image without label; expected {labels_dir / (case_id + ending)}"
                )
            pairs.append((case_id, image, label_files[case_id]))
        orphans = sorted(set(label_files) - seen)
        if orphans:
            raise CohortError(
                f"{labels_dir}: {len(orphans)} label(s) without an image in {images_dir.name}/ "
                f"({', '.join(orphans[:5])}); the file names must match "
                f"(<case>{ending} or <case>_0000{ending})"
            )
    if not pairs:
        raise CohortError(f"{root}: empty cohort, no images ending in {ending} in imagesTr/")
    ids = [p[0] for p in pairs]
    if len(set(ids)) != len(ids):
        raise CohortError(f"{root}: duplicate case ids in the training list")

    subjects_path = root / "subjects.csv"
    subjects = _read_subjects(subjects_path, ids) if subjects_path.is_file() else {}
    landmarks_dir = root / "landmarksTr"
    cases = [
        Case(
            case_id=case_id,
            subject=subjects.get(case_id, case_id),
            image=image,
            label=label,
            landmarks=_find_landmark_file(landmarks_dir, case_id),
        )
        for case_id, image, label in pairs
    ]
    return Cohort(cases=cases, labels=labels, name=str(spec.get("name", root.name)), root=root)


def _load_manifest(path: Path) -> Cohort:
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            header = [c.strip() for c in (reader.fieldnames or [])]
            rows = list(reader)
    except UnicodeDecodeError:
        raise CohortError(f"{path}: not a text CSV manifest") from None
    unknown = [c for c in header if c not in _MANIFEST_COLUMNS]
    if unknown:
        raise CohortError(
            f"{path}: unknown manifest column(s) {unknown}; allowed: image, label, and "
            "optionally subject (or subject_key), landmarks, case_id (or case)"
        )
    for required in ("image", "label"):
        if required not in header:
            raise CohortError(f"{path}: manifest needs an {required!r} column, found {header}")
    if not rows:
        raise CohortError(f"{path}: empty cohort, the manifest has no rows")
    base = path.parent
    cases = []
    for line, raw in enumerate(rows, start=2):
        row = {_MANIFEST_COLUMNS[k.strip()]: (v or "").strip() for k, v in raw.items() if k}

        def resolve(column: str, *, row=row, line=line) -> Path | None:
            value = row.get(column, "")
            if not value:
                return None
            p = Path(value).expanduser()
            p = p if p.is_absolute() else base / p
            if not p.exists():
                raise CohortError(f"{path}, line {line}: {column} file {p} does not exist")
            return p

        image = resolve("image")
        if image is None:
            raise CohortError(f"{path}, line {line}: empty 'image'")
        label = resolve("label")
        if label is None:
            raise CohortError(f"{path}, line {line}: image without label ({image.name})")
        case_id = row.get("case_id") or _case_id_from_image(image.name, _ending(image.name))[0]
        cases.append(
            Case(
                case_id=case_id,
                subject=row.get("subject") or case_id,
                image=image,
                label=label,
                landmarks=resolve("landmarks"),
            )
        )
    ids = [c.case_id for c in cases]
    duplicates = sorted({i for i in ids if ids.count(i) > 1})
    if duplicates:
        raise CohortError(
            f"{path}: duplicate case ids {duplicates[:5]}; add a case_id column to tell them apart"
        )
    return Cohort(cases=cases, labels={}, name=path.stem, root=path)


def _ending(name: str) -> str:
    for ending in (".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd"):
        if name.endswith(ending):
            return ending
    return Path(name).suffix


def load_cohort(path: str | os.PathLike) -> Cohort:
    """Discover a cohort from an MSD / nnU-Net folder or a CSV manifest.

    Parameters
    ----------
    path : path-like
        * A folder in the MSD / nnU-Net layout: ``imagesTr/`` and ``labelsTr/``, usually a
          ``dataset.json`` whose ``labels`` are in MSD (``{"1": "name"}``) or nnU-Net v2
          (``{"name": 1}``) form. Cases come from its ``training`` list when present, else
          from matching file names (``<case>.nii.gz`` or ``<case>_0000.nii.gz`` in
          ``imagesTr/`` with ``<case>.nii.gz`` in ``labelsTr/``; ``file_ending`` honoured).
          A ``subjects.csv`` beside it (columns ``case`` and ``subject_key``) groups cases by
          subject, otherwise each case is its own subject. Landmark files
          ``landmarksTr/<case>.csv`` (or ``.fcsv`` / ``.mrk.json``) are picked up.
        * A ``.csv`` manifest with columns ``image``, ``label`` and optionally ``subject``,
          ``landmarks``, ``case_id``; relative paths are resolved against the CSV's folder.

    Returns
    -------
    cohort : Cohort
        Cases hold file paths; images are read on demand (``case.load_image()``).

    Raises
    ------
    CohortError
        Missing folder or file, empty cohort, an image without label or a label without
        image, unknown manifest columns, incomplete ``subjects.csv``; the message names the
        path.
    """
    path = Path(path).expanduser()
    if not path.exists():
        raise CohortError(
            f"cohort {path} does not exist; give an MSD / nnU-Net folder or a CSV manifest"
        )
    if path.is_dir():
        return _load_msd(path.resolve())
    if path.suffix.lower() == ".csv":
        return _load_manifest(path.resolve())
    raise CohortError(
        f"{path}: not a cohort; give an MSD / nnU-Net folder (with imagesTr/, labelsTr/) or a "
        ".csv manifest"
    )


# ----------------------------------------------------------------------------- phantom


def make_phantom_cohort(
    n_subjects: int = 20,
    *,
    n_landmarks: int = 30,
    anisotropic: bool = False,
    oblique: bool = False,
    random_state=None,
    n_surface_points: int = 2000,
    size: int = 64,
    max_rotation_deg: float = 30.0,
    scale_range: tuple[float, float] = (0.8, 1.25),
    max_translation_mm: float = 4.0,
    shape_variation: float = 1.0,
    neighbour_contrast: tuple[float, float] = (0.04, 0.08),
    n_distractors: int = 3,
    bias_strength: float = 0.15,
    noise_std: float = 0.06,
) -> Cohort:
    """Synthetic cohort: a bent, tapered, bumpy bean pressed against look-alike neighbours.

    The package's embedded default data and the benchmark of the whole pipeline. The target
    (label 1) is a star-shaped surface given by a radial function over the sphere in a
    straight frame (tapered ellipsoid, ~30 mm long, with a bump and a notch), whose long axis
    is bent along a circular arc; five smooth modes (length, thickness, taper, bend, bump
    height) vary it across subjects. It has no mirror or rotational symmetry. Two neighbour
    blobs with intensity within ``neighbour_contrast`` of the target's overlap part of its
    surface, so its boundary is visible only there where they do not touch it. The
    background is a smooth texture with distractor blobs. Each subject is posed by a random
    similarity transform, then a smooth multiplicative bias field and Rician noise are
    applied.

    Parameters
    ----------
    n_subjects : int, default 20
        One case per subject.
    n_landmarks : int, default 30
        Landmark sites, spread evenly (farthest-point sampling) over the mean surface.
    anisotropic : bool, default False
        1 x 1 x 2 mm (x, y, z) voxels instead of 1 mm isotropic; same field of view.
    oblique : bool, default False
        Tilt the image axes by 20 degrees about a random axis (per subject).
    random_state : int, RandomState or None
        Subject ``i`` depends only on the seed and ``i``: a cohort of 5 is the first five
        subjects of a cohort of 20 built with the same seed.
    n_surface_points : int, default 2000
        Dense corresponding surface sites in ``meta["surface_points"]``.
    size : int, default 64
        Field of view in mm along each axis (voxels at 1 mm).
    max_rotation_deg : float, default 30
        Rotation angle drawn uniformly in ``[0, max_rotation_deg]`` about a uniformly random
        axis.
    scale_range : (float, float), default (0.8, 1.25)
        Isotropic scale, log-uniform.
    max_translation_mm : float, default 4
        Translation drawn uniformly in ``[-t, t]`` mm per axis.
    shape_variation : float, default 1
        Standard deviation multiplier of the shape modes (0 gives the mean shape).
    neighbour_contrast : (float, float), default (0.04, 0.08)
        Relative intensity difference of the neighbours to the target (either sign).
    n_distractors : int, default 3
        Background blobs at 70-85 % of the target intensity, away from the target.
    bias_strength : float, default 0.15
        Peak relative amplitude of the multiplicative bias field.
    noise_std : float, default 0.06
        Rician noise standard deviation relative to the target intensity (100).

    Returns
    -------
    cohort : Cohort
        In-memory cases ``phantom_000``, ... with ``image`` (float32) and ``label`` (uint8,
        1 = target) SimpleITK images, ``landmarks`` (n_landmarks, 3) mm (x, y, z) and
        ``meta``:

        * ``surface_points`` (n_surface_points, 3) mm: boundary points, the same parametric
          sites in every subject;
        * ``landmark_index`` (n_landmarks,): indices of the landmarks into surface_points;
        * ``pose``: ``{"rotation": (3, 3), "scale": float, "translation": (3,)}`` with
          ``surface_points = scale * canonical_points @ rotation.T + translation``;
        * ``canonical_points`` (n_surface_points, 3) mm, ``rotation_deg``, ``shape_modes``
          (5,), ``contact`` (n_surface_points,) bool: sites touched by a neighbour,
          ``neighbour_intensity_ratio``, ``spacing``.

    Examples
    --------
    >>> cohort = make_phantom_cohort(2, random_state=0)
    >>> len(cohort), cohort[0].landmarks.shape
    (2, (30, 3))
    """
    if int(n_subjects) < 1:
        raise ParameterError(f"`n_subjects` must be at least 1, got {n_subjects}")
    if not 3 <= int(n_landmarks) <= int(n_surface_points):
        raise ParameterError(
            f"`n_landmarks` must be between 3 and n_surface_points={n_surface_points}, "
            f"got {n_landmarks}"
        )
    if not 0 < scale_range[0] <= scale_range[1]:
        raise ParameterError(f"`scale_range` must be 0 < low <= high, got {scale_range}")
    rng = check_random_state(random_state)
    seeds = rng.randint(0, np.iinfo(np.int32).max, size=int(n_subjects))
    landmark_index = phantom_landmark_index(int(n_landmarks), int(n_surface_points))
    cases = []
    for i, seed in enumerate(seeds):
        image, label, meta = make_phantom_case(
            int(seed),
            n_surface_points=int(n_surface_points),
            landmark_index=landmark_index,
            size=int(size),
            anisotropic=anisotropic,
            oblique=oblique,
            max_rotation_deg=float(max_rotation_deg),
            scale_range=(float(scale_range[0]), float(scale_range[1])),
            max_translation_mm=float(max_translation_mm),
            shape_variation=float(shape_variation),
            neighbour_contrast=neighbour_contrast,
            n_distractors=int(n_distractors),
            bias_strength=float(bias_strength),
            noise_std=float(noise_std),
        )
        case_id = f"phantom_{i:03d}"
        cases.append(
            Case(
                case_id=case_id,
                subject=case_id,
                image=image,
                label=label,
                landmarks=meta["surface_points"][landmark_index].copy(),
                meta=meta,
            )
        )
    return Cohort(cases=cases, labels={"background": 0, "target": 1}, name="phantom", root=None)


# ----------------------------------------------------------------------------- writing


def write_cohort(cohort: Cohort, folder: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Write a cohort in the MSD / nnU-Net layout, readable by :func:`load_cohort`.

    Writes ``dataset.json`` (nnU-Net v2 name -> int labels, ``channel_names``,
    ``file_ending``, ``numTraining`` and an MSD ``training`` list),
    ``imagesTr/<case>_0000.nii.gz``, ``labelsTr/<case>.nii.gz``, ``landmarksTr/<case>.csv``
    for cases with landmarks, and ``subjects.csv`` (``case``, ``subject_key``). Everything
    is written into a temporary folder beside ``folder``, which is renamed into place at
    the end: a failed run leaves nothing behind.

    Parameters
    ----------
    cohort : Cohort
    folder : path-like
        Must not exist, or be empty (or ``overwrite=True``).
    overwrite : bool, default False
        Replace an existing non-empty folder (never one that holds the cohort's own input
        files).

    Returns
    -------
    folder : Path

    Raises
    ------
    CohortError
        Empty cohort, a case without label, duplicate case ids.
    InputFileError
        ``folder`` exists and is not empty (without ``overwrite``), or holds input files.
    """
    folder = Path(folder).expanduser().absolute()
    if len(cohort) == 0:
        raise CohortError(f"cannot write {folder}: the cohort is empty")
    ids = [c.case_id for c in cohort]
    if len(set(ids)) != len(ids):
        raise CohortError(f"cannot write {folder}: duplicate case ids in the cohort")
    if folder.exists():
        if not folder.is_dir():
            raise InputFileError(f"cannot write cohort to {folder}: it is a file")
        if any(folder.iterdir()) and not overwrite:
            raise InputFileError(
                f"cannot write cohort to {folder}: folder exists and is not empty; choose a "
                "new folder or pass overwrite=True"
            )
        for case in cohort:
            for source in (case.image, case.label, case.landmarks):
                if isinstance(source, str | os.PathLike) and Path(source).absolute().is_relative_to(
                    folder
                ):
                    raise InputFileError(
                        f"cannot write cohort to {folder}: it holds the input file {source}"
                    )
    with atomic_folder(folder) as staging:
        for sub in ("imagesTr", "labelsTr"):
            (staging / sub).mkdir()
        training, rows = [], []
        for case in cohort:
            if case.label is None:
                raise CohortError(f"cannot write {folder}: case {case.case_id!r} has no label")
            image = case.load_image()
            label = case.load_label()
            image_rel = f"imagesTr/{case.case_id}_0000.nii.gz"
            label_rel = f"labelsTr/{case.case_id}.nii.gz"
            write_image(image, staging / image_rel)
            write_image(label, staging / label_rel)
            row = {
                "case": case.case_id,
                "subject_key": case.subject,
                "image": image_rel,
                "label": label_rel,
                "landmarks": "",
            }
            landmarks = case.load_landmarks()
            if landmarks is not None:
                (staging / "landmarksTr").mkdir(exist_ok=True)
                row["landmarks"] = f"landmarksTr/{case.case_id}.csv"
                write_landmarks(landmarks, staging / row["landmarks"])
            training.append({"image": f"./{image_rel}", "label": f"./{label_rel}"})
            rows.append(row)
        labels = dict(cohort.labels) or {"background": 0, "foreground": 1}
        spec = {
            "name": cohort.name,
            "channel_names": {"0": "image"},
            "labels": labels,
            "numTraining": len(training),
            "file_ending": ".nii.gz",
            "training": training,
        }
        (staging / "dataset.json").write_text(json.dumps(spec, indent=1) + "\n", encoding="utf-8")
        with open(staging / "subjects.csv", "w", newline="", encoding="utf-8") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    return folder
