"""Zip archives from untrusted sources (NPZ arrays, skops files), checked before reading.

A model file may come from someone else. Everything a zip archive declares is checked from
its directory and the ``.npy`` headers of its members before any member is decompressed:

* the end-of-central-directory record exists (a truncated or foreign file has none), and the
  directory is small (a directory of millions of entries is itself a memory bomb);
* member names are plain relative names, without duplicates;
* the declared uncompressed sizes sum to at most ``max_bytes`` (Python's ``zipfile`` stops
  decompressing a member at its declared size, so the declaration bounds the memory);
* each ``.npy`` member has a valid header, no Python objects (``allow_pickle`` would be
  needed), and exactly as many data bytes as its shape and dtype declare: numpy allocates the
  declared array before reading it.
"""

from __future__ import annotations

import math
import os
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np

from medseg.errors import ModelFileError

__all__ = ["MAX_UNPACKED_BYTES", "MAX_MEMBERS", "check_archive"]

#: Largest total uncompressed size accepted for one archive (bytes).
MAX_UNPACKED_BYTES = 4 * 1024**3
#: Most members accepted in one archive.
MAX_MEMBERS = 100_000
_EOCD = b"PK\x05\x06"
_EOCD_SIZE = 22
_MAX_COMMENT = 0xFFFF


def _directory(path: Path) -> tuple[int, int]:
    """``(n_entries, directory_bytes)`` from the end-of-central-directory record."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        tail_size = min(size, _EOCD_SIZE + _MAX_COMMENT)
        fh.seek(size - tail_size)
        tail = fh.read(tail_size)
    at = tail.rfind(_EOCD)
    if at < 0 or len(tail) - at < _EOCD_SIZE:
        raise ModelFileError(
            f"{path}: not a zip archive (no end-of-directory record); the file is truncated, "
            "corrupt or not a medseg model file"
        )
    n_entries, directory_bytes = struct.unpack("<HI", tail[at + 10 : at + 16])
    return n_entries, directory_bytes


def _npy_problem(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> str | None:
    """Why a ``.npy`` member cannot be loaded safely, or None."""
    try:
        with zf.open(info) as fh:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(fh, max_header_size=10_000)
            else:
                shape, _, dtype = np.lib.format.read_array_header_2_0(fh, max_header_size=10_000)
            header_bytes = fh.tell()
    except (
        ValueError,
        OSError,
        EOFError,
        zipfile.BadZipFile,
        zlib.error,
        NotImplementedError,
    ) as exc:
        return f"member {info.filename!r} is not a valid .npy array ({exc})"
    if dtype.hasobject:
        return f"member {info.filename!r} holds Python objects (would need pickle)"
    declared = math.prod(int(n) for n in shape) * dtype.itemsize
    if header_bytes + declared != info.file_size:
        return (
            f"member {info.filename!r} declares a {dtype} array of shape {tuple(shape)} "
            f"({declared} bytes) but holds {info.file_size - header_bytes} bytes of data"
        )
    return None


def check_archive(path: str | os.PathLike, *, max_bytes: int | None = None) -> int:
    """Check a zip archive (``.npz``, ``.skops``) from its directory, without unpacking it.

    Parameters
    ----------
    path : path-like
        The archive.
    max_bytes : int, optional
        Largest accepted total uncompressed size; default :data:`MAX_UNPACKED_BYTES`.

    Returns
    -------
    n_bytes : int
        Total declared uncompressed size of the members.

    Raises
    ------
    ModelFileError
        Not a zip archive, too many members, unsafe or duplicate member names, declared
        content above ``max_bytes``, or a ``.npy`` member whose header is invalid, holds
        Python objects or does not match its size. The message names the file.
    """
    path = Path(path)
    limit = MAX_UNPACKED_BYTES if max_bytes is None else int(max_bytes)
    n_entries, directory_bytes = _directory(path)
    if n_entries > MAX_MEMBERS or directory_bytes > MAX_MEMBERS * 1024:
        raise ModelFileError(
            f"{path}: archive directory lists {n_entries} members in {directory_bytes} bytes "
            f"(at most {MAX_MEMBERS} members in {MAX_MEMBERS * 1024} bytes accepted); refusing "
            "to read it"
        )
    try:
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
            names = [info.filename for info in infos]
            unsafe = [
                n
                for n in names
                if n.startswith(("/", "\\")) or ".." in n.replace("\\", "/").split("/")
            ]
            if unsafe or len(set(names)) != len(names):
                raise ModelFileError(
                    f"{path}: archive has unsafe or duplicate member names "
                    f"{(unsafe or sorted(n for n in set(names) if names.count(n) > 1))[:3]}; "
                    "it was not written by medseg"
                )
            total = sum(info.file_size for info in infos)
            if total > limit:
                raise ModelFileError(
                    f"{path}: archive declares {total / 1e9:.1f} GB of uncompressed content, "
                    f"above the limit of {limit / 1e9:.1f} GB; refusing to unpack it"
                )
            for info in infos:
                if info.filename.endswith(".npy"):
                    problem = _npy_problem(zf, info)
                    if problem:
                        raise ModelFileError(f"{path}: {problem}; the file is corrupt or forged")
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, zlib.error) as exc:
        raise ModelFileError(
            f"{path}: malformed zip archive ({exc}); the file is corrupt or not a medseg model file"
        ) from None
    return total
