"""What a cross-validation run leaves on disk: the per-case CSV and the predicted label maps.

* :data:`COLUMNS`: the columns of ``cases.csv``, one row per (method, fold, case,
  perturbation condition): ``perturbation`` is the condition's name
  (:mod:`medseg.evaluation.perturbation`, ``acquired`` for the unperturbed case),
  ``perturbation_deg`` and ``scale`` the rotation angle and scale it applied to that case;
  :data:`SCORES` are the scores among them, which the report summarises;
* :func:`read_results`: the typed rows of a ``cases.csv`` (a torn last line, left by a run
  that was killed mid-write, is dropped; a file of an older version, without the
  ``perturbation`` column, is refused with an :class:`~medseg.errors.InputFileError`);
* :class:`ResultsFile`: the CSV a run appends to, one flushed row at a time, so that a rerun
  on the same folder resumes after the rows already there (:func:`result_key` identifies a
  row);
* :func:`prediction_path`: where a method's label map of a case is written.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np

from medseg.errors import InputFileError
from medseg.io import atomic_write

__all__ = [
    "SCORES",
    "COLUMNS",
    "read_results",
    "result_key",
    "ResultsFile",
    "prediction_path",
]

#: The scores of one segmentation, in column order (what the report summarises).
SCORES = (
    "dice",
    "hd95",
    "assd",
    "landmark_error_mm",
    "landmark_error_vox",
    "gap",
)

#: Columns of the per-case CSV, in order.
COLUMNS = (
    "method",
    "fold",
    "case",
    "subject",
    "perturbation",
    "perturbation_deg",
    "scale",
    *SCORES,
    "dice_by_label",
    "quality",
    "seconds",
    "fit_seconds",
)
#: Columns a file of an earlier version may lack, and the value their rows then take:
#: ``dice_by_label``, the Dice of each label of a reference of several ("1:0.89;2:0.87");
#: ``quality``, the segmenter's ``Segmentation.quality["score"]`` (NaN for methods without).
_OPTIONAL = {"dice_by_label": "", "quality": "nan"}
_FLOAT_COLUMNS = tuple(
    c for c in COLUMNS[COLUMNS.index("perturbation_deg") :] if c != "dice_by_label"
)


def _format(value) -> str:
    if isinstance(value, float | np.floating):
        return repr(float(value))
    return str(value)


def _parse(row: dict) -> dict | None:
    # an optional column absent, or empty, takes its default
    given = {k: v for k, v in row.items() if v not in (None, "") or k not in _OPTIONAL}
    row = {**_OPTIONAL, **given}
    if set(COLUMNS) - set(row) or any(row[c] is None for c in COLUMNS):
        return None
    try:
        out = {c: row[c] for c in COLUMNS}
        out["fold"] = int(row["fold"])
        for c in _FLOAT_COLUMNS:
            out[c] = float(row[c])
    except (TypeError, ValueError):
        return None
    return out


def read_results(path: str | os.PathLike) -> list[dict]:
    """Rows of a per-case CSV written by :func:`medseg.evaluation.runner.run_folds`.

    Typed (``fold`` an int, the scores and times floats); torn lines are dropped, and a
    missing (or empty) file has no rows.

    Raises
    ------
    InputFileError
        The header lacks some of :data:`COLUMNS`: a file of another version (before the
        ``perturbation`` column, rows were keyed by angle alone), which cannot be resumed
        or reported; its rows are not dropped silently.
    """
    path = Path(path)
    if not path.is_file():
        return []
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        missing = [
            c for c in COLUMNS if c not in (reader.fieldnames or COLUMNS) and c not in _OPTIONAL
        ]
        if missing:
            raise InputFileError(
                f"{path} lacks the column(s) {', '.join(missing)}: it was written by another "
                "version of medseg-evaluate; choose a new output folder (or move the file "
                "away) to run again"
            )
        rows = [_parse(r) for r in reader]
    return [r for r in rows if r is not None]


def result_key(method: str, fold: int, case: str, condition: str) -> tuple:
    """What identifies a row: method, fold, case and perturbation condition (its name).

    The name, not the angle: ``acquired``, ``pad_zeros`` and ``scale0.8`` all rotate by 0
    degrees. Within a run (one seed, checked by the runner) a name gives each case one
    perturbed copy.
    """
    return (str(method), int(fold), str(case), str(condition))


def _row_key(row: dict) -> tuple:
    return result_key(row["method"], row["fold"], row["case"], row["perturbation"])


class ResultsFile:
    """The per-case CSV: rewritten clean on open (drops a torn last line), then appended.

    Attributes
    ----------
    path : pathlib.Path
    done : set of tuple
        :func:`result_key` of every row in the file.
    """

    def __init__(self, path: Path):
        self.path = path
        rows = read_results(path)
        with atomic_write(path) as tmp:
            with tmp.open("w", newline="", encoding="utf-8") as fh:
                writer = csv.DictWriter(fh, fieldnames=COLUMNS)
                writer.writeheader()
                for r in rows:
                    writer.writerow({c: _format(r[c]) for c in COLUMNS})
        self.done = {_row_key(r) for r in rows}

    def append(self, row: dict) -> None:
        """Write one row and flush it to disk before returning."""
        with self.path.open("a", newline="", encoding="utf-8") as fh:
            csv.DictWriter(fh, fieldnames=COLUMNS).writerow({c: _format(row[c]) for c in COLUMNS})
            fh.flush()
            os.fsync(fh.fileno())
        self.done.add(_row_key(row))


def prediction_path(folder: str | os.PathLike, method: str, case_id: str) -> Path:
    """Where the label map predicted by ``method`` for ``case_id`` is written."""
    return Path(folder) / method / f"{case_id}.nii.gz"
