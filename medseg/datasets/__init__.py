"""Cohorts: discovery from MSD / nnU-Net folders and CSV manifests, and the synthetic phantom.

A :class:`Cohort` is a sequence of :class:`Case` objects (image, label map, optional
landmarks) that knows each case's *subject*: cases of one person share a subject key, so
cross-validation can split by subject (``GroupKFold(groups=cohort.subjects)``).

* :func:`load_cohort` reads an MSD / nnU-Net folder (``dataset.json``, ``imagesTr/``,
  ``labelsTr/``, optional ``landmarksTr/`` and ``subjects.csv``) or a CSV manifest.
* :func:`make_phantom_cohort` generates the package's embedded synthetic cohort.
* :func:`write_cohort` writes any cohort in the MSD layout, so every CLI can run on it.

One idea per module: ``_cohort`` (the data model), ``_names`` (case ids from file names),
``_msd`` and ``_manifest`` (the two on-disk forms), ``_load`` (:func:`load_cohort`, which
tells them apart), ``_write`` (:func:`write_cohort`), and the phantom in three layers:
``_phantom_shape`` (its anatomy and surface sites), ``_phantom_image`` (one subject's image
and label) and ``_phantom`` (the cohort).
"""

from medseg.datasets._cohort import Case, Cohort
from medseg.datasets._load import load_cohort
from medseg.datasets._phantom import make_phantom_cohort
from medseg.datasets._phantom_shape import phantom_landmark_index
from medseg.datasets._write import write_cohort

__all__ = [
    "Case",
    "Cohort",
    "load_cohort",
    "make_phantom_cohort",
    "write_cohort",
    "phantom_landmark_index",
]
