"""The one entry for cohorts on disk: :func:`load_cohort` tells a folder from a manifest.

A folder is read as the MSD / nnU-Net layout (:mod:`._msd`), a ``.csv`` file as a manifest
(:mod:`._manifest`); anything else is refused with a message saying what would do.
"""

from __future__ import annotations

import os
from pathlib import Path

from medseg.datasets._cohort import Cohort
from medseg.datasets._manifest import _load_manifest
from medseg.datasets._msd import _load_msd
from medseg.errors import CohortError


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
