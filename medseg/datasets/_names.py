"""Case ids from image file names: the naming conventions both on-disk forms rely on.

An MSD / nnU-Net image is ``<case>.nii.gz`` or ``<case>_0000.nii.gz`` (a channel suffix of
four digits); a manifest row without a ``case_id`` and a ``subjects.csv`` naming images get
their case id the same way, so these rules live here once.
"""

from __future__ import annotations

from pathlib import Path

from medseg.io import IMAGE_SUFFIXES


def _strip_ending(name: str, ending: str) -> str | None:
    return name[: -len(ending)] if name.endswith(ending) else None


def _case_id_from_image(name: str, ending: str) -> tuple[str, str | None]:
    """Case id and channel (``"0000"``) of an image file name, channel None if absent."""
    stem = _strip_ending(name, ending) or name
    head, sep, channel = stem.rpartition("_")
    if sep and len(channel) == 4 and channel.isdigit():
        return head, channel
    return stem, None


def _ending(name: str) -> str:
    """The image-format ending of a file name (``.nii.gz`` counts as one), case as written."""
    return next((e for e in IMAGE_SUFFIXES if name.endswith(e)), Path(name).suffix)
