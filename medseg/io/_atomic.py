"""Atomic writes: a temporary folder beside the target, then ``os.replace`` into place."""

from __future__ import annotations

import os
import secrets
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from medseg.errors import InputFileError

__all__ = ["atomic_folder", "atomic_write", "check_not_protected"]

PathLike = str | os.PathLike


def _same_file(a: Path, b: Path) -> bool:
    """Whether two paths name the same file (hard links and symlinks included)."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet): compare resolved paths
        return a.resolve() == b.resolve()


def check_not_protected(path: PathLike, protect: Iterable[PathLike] = ()) -> None:
    """Raise :class:`InputFileError` if ``path`` is one of the ``protect`` paths.

    Parameters
    ----------
    path : path-like
        The file about to be written.
    protect : iterable of path-like
        Input files that must never be overwritten. Compared with :func:`os.path.samefile`
        when both exist, else by resolved path.
    """
    target = Path(path)
    for item in protect:
        if item is None:
            continue
        if _same_file(target, Path(item)):
            raise InputFileError(
                f"refusing to write {str(target)!r}: it is an input file ({str(item)!r}); "
                "choose another output path"
            )


@contextmanager
def atomic_write(path: PathLike, *, protect: Iterable[PathLike] = ()) -> Iterator[Path]:
    """Context manager that yields a temporary path to write, then moves it onto ``path``.

    The temporary path is ``<folder>/.tmp-<random>-<name>.part/<name>``: it sits in the target
    folder (so the final :func:`os.replace` is a rename on one file system, atomic on POSIX)
    and keeps the real file name and suffix, so writers that choose their format from the
    name (SimpleITK, nibabel) behave exactly as for ``path``. Companion files the writer puts
    beside it (a MetaImage ``.mhd`` writes ``name.raw`` / ``name.zraw`` too) are moved as
    well, data files first and the named file last. If the body raises, the temporary folder
    and everything in it are removed and nothing at ``path`` changes. (Only a killed process
    can leave a ``.tmp-*.part`` folder behind; its name matches no image or landmark glob.)

    Parameters
    ----------
    path : path-like
        Final file. Its parent folder is created if missing.
    protect : iterable of path-like, optional
        Input files that must not be overwritten; writing onto one of them (or onto a
        companion file that is one of them) raises :class:`~medseg.errors.InputFileError`
        before anything is written.

    Yields
    ------
    tmp_path : pathlib.Path
        Where to write.

    Raises
    ------
    InputFileError
        ``path`` is a protected input, an existing folder, or its folder cannot be created.

    Examples
    --------
    >>> with atomic_write("/tmp/out.nii.gz") as tmp:  # doctest: +SKIP
    ...     sitk.WriteImage(image, str(tmp))
    """
    target = Path(path)
    protect = [p for p in protect if p is not None]
    check_not_protected(target, protect)
    if target.is_dir():
        raise InputFileError(f"cannot write {str(target)!r}: it is an existing folder")
    folder = target.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputFileError(f"cannot create the output folder {str(folder)!r}: {exc}") from exc
    tmp_dir = folder / f".tmp-{secrets.token_hex(6)}-{target.name}.part"
    try:
        tmp_dir.mkdir()
    except OSError as exc:
        raise InputFileError(f"cannot write into the folder {str(folder)!r}: {exc}") from exc
    try:
        tmp_path = tmp_dir / target.name
        yield tmp_path
        if not tmp_path.exists():
            raise InputFileError(f"nothing was written for {str(target)!r}")
        produced = sorted(tmp_dir.iterdir(), key=lambda p: p.name == target.name)
        for item in produced:
            check_not_protected(folder / item.name, protect)
        for item in produced:  # companions first, the named file last
            os.replace(item, folder / item.name)
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)


@contextmanager
def atomic_folder(path: PathLike) -> Iterator[Path]:
    """Build a whole folder (a model, a cohort) in a staging folder, then swap it into place.

    Yields an empty staging folder beside ``path``. On success an existing ``path`` is moved
    aside, the staging folder renamed to ``path`` and the old one removed; on any exception
    the staging folder is removed and ``path`` is left as it was.
    """
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=parent))
    try:
        yield staging
        if path.exists():
            trash = Path(tempfile.mkdtemp(prefix=f".{path.name}.old-", dir=parent))
            os.replace(path, trash / path.name)
            os.replace(staging, path)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.replace(staging, path)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
