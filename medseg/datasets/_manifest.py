"""Reading a cohort from a CSV manifest: one row per case, paths relative to the CSV.

Columns ``image`` and ``label`` (required), ``subject`` (or ``subject_key``), ``landmarks``
and ``case_id`` (or ``case``); any other column is refused rather than ignored, so that a
misspelt ``subjekt`` does not silently make every case its own subject.
"""

from __future__ import annotations

import csv
from pathlib import Path

from medseg.datasets._cohort import Case, Cohort
from medseg.datasets._names import _case_id_from_image, _ending
from medseg.errors import CohortError

_MANIFEST_COLUMNS = {
    "image": "image",
    "label": "label",
    "subject": "subject",
    "subject_key": "subject",
    "landmarks": "landmarks",
    "case_id": "case_id",
    "case": "case_id",
}


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
