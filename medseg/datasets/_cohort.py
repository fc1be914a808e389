"""The data model: a :class:`Case` (image, label map, landmarks, subject) and a :class:`Cohort`.

Everything else in :mod:`medseg.datasets` produces or consumes these. A case holds either
file paths, read on demand, or in-memory SimpleITK images (the phantom), so the same code
trains on both; a cohort knows each case's subject, the groups of a subject-wise split.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from medseg.errors import LabelError
from medseg.io import read_image, read_label, read_landmarks


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
