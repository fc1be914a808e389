"""Reading a cohort from a folder in the MSD / nnU-Net layout.

``imagesTr/`` and ``labelsTr/``, usually a ``dataset.json`` (labels in either MSD or nnU-Net
v2 form, an optional ``training`` list and ``file_ending``), optional ``landmarksTr/`` and
``subjects.csv``. Every inconsistency (an image without label, an orphan label, a duplicate
case, an incomplete ``subjects.csv``) is a :class:`~medseg.errors.CohortError` naming the
path, because this is where users' own data first meets the package.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

from medseg.datasets._cohort import Case, Cohort
from medseg.datasets._names import _case_id_from_image, _strip_ending
from medseg.errors import CohortError

_LANDMARK_SUFFIXES = (".mrk.json", ".fcsv", ".csv")


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


def _read_spec(spec_path: Path) -> dict:
    """``dataset.json`` as a dict; an empty dict when there is none."""
    spec: dict = {}
    if spec_path.is_file():
        try:
            spec = json.loads(spec_path.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise CohortError(f"{spec_path}: not valid JSON ({exc})") from None
        if not isinstance(spec, dict):
            raise CohortError(f"{spec_path}: expected a JSON object")
    return spec


def _pairs_from_training_list(
    root: Path, spec: dict, spec_path: Path, ending: str
) -> list[tuple[str, Path, Path]]:
    """(case id, image, label) of every entry of the ``training`` list of ``dataset.json``."""
    pairs = []
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
    return pairs


def _pairs_from_file_names(
    images_dir: Path, labels_dir: Path, ending: str
) -> list[tuple[str, Path, Path]]:
    """(case id, image, label) matched by file name: ``<case>[_0000]<ending>`` to ``<case>``."""
    label_files = {_strip_ending(p.name, ending): p for p in _visible_files(labels_dir, ending)}
    seen: set[str] = set()
    pairs = []
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
    return pairs


def _load_msd(root: Path) -> Cohort:
    images_dir, labels_dir = root / "imagesTr", root / "labelsTr"
    for folder in (images_dir, labels_dir):
        if not folder.is_dir():
            raise CohortError(
                f"{root}: missing folder {folder.name}/; an MSD / nnU-Net cohort has "
                "dataset.json, imagesTr/ and labelsTr/"
            )
    spec_path = root / "dataset.json"
    spec = _read_spec(spec_path)
    labels = _labels_from_json(spec["labels"], spec_path) if "labels" in spec else {}
    ending = str(spec.get("file_ending", ".nii.gz"))

    if isinstance(spec.get("training"), list) and spec["training"]:
        pairs = _pairs_from_training_list(root, spec, spec_path, ending)
    else:
        pairs = _pairs_from_file_names(images_dir, labels_dir, ending)
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
