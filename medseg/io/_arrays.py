"""Named arrays with a JSON header in one NPZ file: how the fitted parts are stored.

Every fitted part of a model that holds only arrays (the triplet prior, the handedness term,
the active shape model) is saved as one ``.npz`` file: its arrays, plus ``header``, a JSON
string naming the format and its version and holding the part's parameters. Writes are
atomic (:func:`medseg.io.atomic_write`); reads refuse pickled objects and check the archive
from its zip directory before anything is unpacked (:func:`check_archive`), so a model
folder received from someone else is safe to open.
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from medseg.errors import InputFileError, ModelFileError
from medseg.io._archive import check_archive
from medseg.io._atomic import atomic_write

__all__ = ["save_arrays", "load_arrays", "check_format"]

_HEADER = "header"


def save_arrays(path: str | os.PathLike, arrays: dict, *, header: dict) -> Path:
    """Write ``arrays`` and the JSON ``header`` to the NPZ file ``path``, atomically.

    Parameters
    ----------
    path : path-like
        Target file; ``.npz`` is appended if missing. Its folder must exist.
    arrays : dict of str -> array
        Numeric arrays (no object arrays: they would need pickle to read).
    header : dict
        JSON-able; by convention ``format``, ``format_version`` and ``params``.

    Returns
    -------
    path : Path
    """
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    if not path.parent.is_dir():
        raise InputFileError(f"cannot save {path}: folder {path.parent} is missing")
    if _HEADER in arrays:
        raise ValueError(f"an array may not be named {_HEADER!r}")
    with atomic_write(path) as tmp:
        np.savez_compressed(
            tmp, **{_HEADER: np.array(json.dumps(header, sort_keys=True))}, **arrays
        )
    return path


def load_arrays(path: str | os.PathLike, *, what: str) -> tuple[dict, dict[str, np.ndarray]]:
    """Read a file written by :func:`save_arrays`: ``(header, arrays)``.

    A file without a header (the handedness term and the active shape model of model
    folders of format version 2 and 3) gives an empty header.

    Parameters
    ----------
    path : path-like
    what : str
        What the file holds, for messages ("triplet prior", ...).

    Raises
    ------
    InputFileError
        The file does not exist.
    ModelFileError
        Not a readable NPZ file, an unsafe archive, or a malformed header.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{what} file {path} does not exist")
    check_archive(path)
    # a damaged member also raises zlib.error (bad deflate data) or NotImplementedError
    # (forged compression flags)
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except (
        OSError,
        ValueError,
        zipfile.BadZipFile,
        EOFError,
        zlib.error,
        NotImplementedError,
    ) as exc:
        raise ModelFileError(
            f"{path} is not a readable {what} file ({exc}); it may be truncated or not a "
            "medseg model"
        ) from None
    if _HEADER not in arrays:
        return {}, arrays
    try:
        header = json.loads(str(arrays.pop(_HEADER)))
    except ValueError as exc:
        raise ModelFileError(f"{path} has no valid JSON header ({exc})") from None
    if not isinstance(header, dict):
        raise ModelFileError(f"{path} has no valid JSON header")
    return header, arrays


def check_format(
    header: dict, *, format: str, version: int, source: str, missing_ok: bool = False
) -> None:
    """Refuse a header of another format, or of a version newer than ``version``.

    ``missing_ok`` accepts an empty header (files written before parts had one).
    """
    if not header and missing_ok:
        return
    if header.get("format") != format:
        raise ModelFileError(f"{source} is not a {format} file (format {header.get('format')!r})")
    found = header.get("format_version")
    if not isinstance(found, int) or not 1 <= found <= version:
        raise ModelFileError(
            f"{source} has {format} format version {found!r}; this medseg reads versions up "
            f"to {version}: upgrade medseg, or refit with this version"
        )
