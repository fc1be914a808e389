"""Writing a cohort in the MSD / nnU-Net layout, so that every CLI can run on any cohort.

The output is what :func:`~medseg.datasets.load_cohort` reads back (``dataset.json`` in both
the nnU-Net v2 and the MSD forms, ``imagesTr/``, ``labelsTr/``, ``landmarksTr/``,
``subjects.csv``); it is staged in a temporary folder and renamed into place, so a failed
run leaves nothing behind, and it never overwrites the cohort's own input files.
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

from medseg.datasets._cohort import Cohort
from medseg.errors import CohortError, InputFileError
from medseg.io import atomic_folder, write_image, write_landmarks


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
