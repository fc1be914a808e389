"""Triangle meshes in and out of files: :func:`read_mesh` and :func:`write_mesh`.

A mesh is a pair of plain arrays: ``vertices`` (V, 3) float (x, y, z) and ``faces`` (F, 3)
int, 0-based. Files are read and written with pyvista (PLY, OBJ, STL, VTK, VTP), except
OFF, which pyvista cannot read without meshio (a small built-in reader and writer), and PLY
files are read with numpy only (VTK's reader crashes on some corrupt ones). Reading checks
values, not topology: that is :func:`medseg.matching.check_mesh`'s.
"""

from __future__ import annotations

import logging
import os
import re
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pyvista as pv
from numpy.typing import ArrayLike

from medseg.errors import InputFileError, MeshError
from medseg.io import atomic_write
from medseg.matching._mesh_check import _check_finite_and_indexed

__all__ = ["read_mesh", "write_mesh", "MESH_SUFFIXES"]

MESH_SUFFIXES = (".off", ".ply", ".obj", ".stl", ".vtk", ".vtp")


def _mesh_suffix(path: Path) -> str:
    """The lower-case suffix of a mesh file; MeshError unless it is in :data:`MESH_SUFFIXES`."""
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshError(
            f"{path}: unsupported mesh format {suffix!r}; use one of {', '.join(MESH_SUFFIXES)}."
        )
    return suffix


def _read_off(path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        tokens = []
        with open(path, encoding="ascii", errors="strict") as fh:
            for line in fh:
                line = line.split("#", 1)[0].strip()
                if line:
                    tokens.extend(line.split())
    except (UnicodeDecodeError, OSError) as exc:
        raise MeshError(f"{path}: cannot read as an ASCII OFF file ({exc}).") from exc
    if not tokens or not tokens[0].upper().endswith("OFF"):
        raise MeshError(f"{path}: not an OFF file (first token is not 'OFF').")
    pos = 1
    if tokens[0].upper() != "OFF":
        raise MeshError(f"{path}: only plain 'OFF' is supported, not {tokens[0]!r}.")
    try:
        n_v, n_f = int(tokens[pos]), int(tokens[pos + 1])
        pos += 3
        vertices = np.asarray(tokens[pos : pos + 3 * n_v], dtype=float)
        if vertices.size != 3 * n_v:
            raise ValueError("truncated vertex list")
        vertices = vertices.reshape(n_v, 3)
        pos += 3 * n_v
        faces = []
        for _ in range(n_f):
            k = int(tokens[pos])
            faces.append([int(t) for t in tokens[pos + 1 : pos + 1 + k]])
            if len(faces[-1]) != k:
                raise ValueError("truncated face list")
            pos += 1 + k
    except (ValueError, IndexError) as exc:
        raise MeshError(f"{path}: malformed OFF file ({exc}); re-export the mesh.") from exc
    if any(len(f) != 3 for f in faces):
        raise MeshError(f"{path}: OFF file has non-triangle faces; triangulate it first.")
    return vertices, np.asarray(faces, dtype=np.int64).reshape(-1, 3)


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


def _ply_header(path: Path, data: bytes) -> tuple[str | None, list, int]:
    """``(byte order or None for ASCII, [(element, count, [(name, type, list count type)])],
    header length)``; MeshError for anything malformed."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise MeshError(f"{path}: not a PLY file (no 'ply' ... 'end_header' header).")
    newline = data.find(b"\n", end)
    if newline < 0:
        raise MeshError(f"{path}: malformed PLY file (nothing after end_header).")
    try:
        lines = data[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError:
        raise MeshError(f"{path}: malformed PLY file (non-ASCII header).") from None
    order, elements = "?", []
    for number, line in enumerate(lines, start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format" and words[1] in _PLY_FORMATS and len(words) == 3:
                order = _PLY_FORMATS[words[1]]
            elif words[0] == "element" and len(words) == 3 and int(words[2]) >= 0:
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and words[1] == "list" and len(words) == 5:
                elements[-1][2].append((words[4], _PLY_TYPES[words[3]], _PLY_TYPES[words[2]]))
            elif words[0] == "property" and len(words) == 3:
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]], None))
            else:
                raise ValueError(line)
        except (ValueError, KeyError, IndexError):
            raise MeshError(f"{path}: malformed PLY header, line {number}: {line!r}.") from None
    if order == "?":
        raise MeshError(f"{path}: malformed PLY header (no valid 'format' line).")
    return order, elements, newline + 1


def _ply_dtype(props: list, order: str, triangle: bool) -> np.dtype:
    """Record dtype of one element, list properties taken as triangles (count + 3 indices)."""
    fields = []
    for name, kind, count_kind in props:
        if count_kind is None:
            fields.append((name, order + kind))
        elif triangle:
            fields += [(name + "#n", order + count_kind), (name, order + kind, (3,))]
        else:
            raise ValueError("list property")
    return np.dtype(fields)


def _read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh from an ASCII or binary PLY file, read with numpy only.

    VTK's PLY reader crashes the process on some corrupt files (found by fuzzing); here every
    count and size is checked against the file before anything is indexed.
    """
    data = path.read_bytes()
    order, elements, start = _ply_header(path, data)
    names = [e[0] for e in elements]
    if "vertex" not in names or "face" not in names:
        raise MeshError(f"{path}: PLY file needs 'vertex' and 'face' elements, has {names}.")
    tables = {}
    if order is None:
        tokens = data[start:].split()
        pos = 0
    for name, count, props in elements:
        is_face = name == "face"
        lists = [p for p in props if p[2] is not None]
        if is_face and (len(lists) != 1 or lists[0][0] not in ("vertex_indices", "vertex_index")):
            raise MeshError(f"{path}: PLY 'face' element needs one vertex_indices list.")
        try:
            dtype = _ply_dtype(props, order or "", triangle=is_face)
        except ValueError:
            raise MeshError(
                f"{path}: PLY element {name!r} has list properties; unsupported."
            ) from None
        if order is None:
            width = len(dtype.names) + (2 if is_face else 0)
            chunk = tokens[pos : pos + count * width]
            pos += count * width
            if len(chunk) != count * width:
                raise MeshError(f"{path}: malformed PLY file (truncated {name!r} data).")
            try:
                table = np.asarray(chunk, dtype=float).reshape(count, width)
            except ValueError:
                raise MeshError(
                    f"{path}: malformed PLY file (non-numeric {name!r} data)."
                ) from None
        else:
            size = count * dtype.itemsize
            if start + size > len(data):
                raise MeshError(
                    f"{path}: malformed PLY file ({name!r} data needs {size} bytes, "
                    f"{len(data) - start} left); re-export the mesh."
                )
            table = np.frombuffer(data, dtype=dtype, count=count, offset=start)
            start += size
        tables[name] = (table, dtype, props)
    vertex, vdtype, vprops = tables["vertex"]
    face, fdtype, fprops = tables["face"]
    vnames = [p[0] for p in vprops]
    if not {"x", "y", "z"} <= set(vnames):
        raise MeshError(f"{path}: PLY vertices lack x, y, z properties ({vnames}).")
    list_name = next(p[0] for p in fprops if p[2] is not None)
    if order is None:
        vertices = vertex[:, [vnames.index(c) for c in "xyz"]]
        column = sum(1 for p in fprops[: [p[0] for p in fprops].index(list_name)])
        counts, faces = face[:, column], face[:, column + 1 : column + 4]
        if np.any(faces != np.round(faces)):
            raise MeshError(f"{path}: malformed PLY file (non-integer face indices).")
    else:
        vertices = np.column_stack([vertex[c] for c in "xyz"])
        counts, faces = face[list_name + "#n"], face[list_name]
    if np.any(counts != 3):
        raise MeshError(f"{path}: PLY file has non-triangle faces; triangulate it first.")
    return np.asarray(vertices, dtype=float), np.asarray(faces, dtype=np.int64).reshape(-1, 3)


_VTK_HEADER = re.compile(
    rb"# vtk DataFile Version \d+\.\d+\r?\n[^\n]{0,256}\n(ASCII|BINARY)\r?\n"
    rb"DATASET (POLYDATA|UNSTRUCTURED_GRID)\r?\n"
)


def _check_legacy_vtk_header(path: Path) -> None:
    """MeshError unless a legacy ``.vtk`` file starts with a well-formed header.

    VTK's legacy reader crashes the process on some malformed headers (found by fuzzing).
    """
    with open(path, "rb") as fh:
        head = fh.read(512)
    if not _VTK_HEADER.match(head):
        raise MeshError(
            f"{path}: not a legacy VTK polygon file (the header must be '# vtk DataFile "
            "Version x.y', a title, ASCII or BINARY, 'DATASET POLYDATA'); re-export the mesh."
        )


def read_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle surface mesh.

    Parameters
    ----------
    path : path-like
        ``.off``, ``.ply``, ``.obj``, ``.stl``, ``.vtk`` or ``.vtp`` file.

    Returns
    -------
    vertices : (V, 3) float array
        Vertex positions, in the file's units (mm for medseg surfaces).
    faces : (F, 3) int64 array
        0-based vertex indices of each triangle.

    Raises
    ------
    InputFileError
        If the file does not exist.
    MeshError
        If the file cannot be parsed, holds no triangles, has NaN or infinite vertex
        coordinates or face indices outside ``[0, V)``. The mesh is not checked for topology
        here: call :func:`check_mesh`. VTK's own messages are kept off stderr.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: mesh file not found.")
    suffix = _mesh_suffix(path)
    if suffix == ".off":
        vertices, faces = _read_off(path)
    elif suffix == ".ply":
        vertices, faces = _read_ply(path)
    else:
        if suffix == ".vtk":
            _check_legacy_vtk_header(path)
        with _quiet_vtk() as errors:
            try:
                mesh = pv.read(str(path))
            except Exception as exc:  # pyvista/VTK raise many types for corrupt files
                errors.insert(0, str(exc))
        if errors:
            reason = _vtk_reason(errors)
            raise MeshError(
                f"{path}: cannot read this {suffix} file, it is corrupt or not a {suffix} mesh "
                f"({reason})."
            )
        if not isinstance(mesh, pv.PolyData):
            try:
                mesh = mesh.extract_surface()
            except Exception as exc:
                raise MeshError(f"{path}: not a surface mesh ({type(mesh).__name__}).") from exc
        if mesh.n_cells and not mesh.is_all_triangles:
            raise MeshError(f"{path}: mesh has non-triangle cells; triangulate it first.")
        vertices = np.asarray(mesh.points, dtype=float)
        faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 4)[:, 1:]
    if len(faces) == 0:
        raise MeshError(f"{path}: mesh has no triangles.")
    _check_finite_and_indexed(
        vertices,
        faces,
        str(path),
        fix_vertices="fix or re-export the mesh",
        fix_faces="; the file is corrupt: re-export the mesh",
    )
    return vertices, faces


def _vtk_reason(errors: list[str]) -> str:
    """The informative part of VTK's messages: ``vtkXReader: text``, without addresses."""
    for text in errors:
        for line in text.splitlines():
            found = re.match(r"\W*(vtk\w+) \(0x[0-9a-fA-F]+\): (.+)", line.strip())
            if found:
                return re.sub(r" \(0x[0-9a-fA-F]+\)", "", f"{found.group(1)}: {found.group(2)}")
    return "the VTK reader failed"


@contextmanager
def _quiet_vtk() -> Iterator[list[str]]:
    """Keep VTK's and pyvista's reader messages off stderr; yield the list of errors seen.

    VTK prints reader errors through its own logger and output window, and pyvista passes
    them on to Python's logging and warnings: a corrupt file would print dozens of lines
    before medseg's one-line error.
    """
    errors: list[str] = []
    previous = logging.root.manager.disable
    logging.disable(logging.CRITICAL)
    try:
        with (
            pv.vtk_verbosity("off"),
            pv.VtkErrorCatcher(send_to_logging=False) as catcher,
            warnings.catch_warnings(record=True) as caught,
        ):
            warnings.simplefilter("always")
            yield errors
        errors.extend(str(event) for event in catcher.error_events)
        errors.extend(str(w.message) for w in caught if "error" in str(w.message).lower())
    finally:
        logging.disable(previous)


def write_mesh(path: str | os.PathLike, vertices: ArrayLike, faces: ArrayLike) -> None:
    """Write a triangle mesh atomically (:func:`medseg.io.atomic_write`).

    Parameters
    ----------
    path : path-like
        Output file; the format follows the suffix (see :data:`MESH_SUFFIXES`).
    vertices : (V, 3) float array
    faces : (F, 3) int array, 0-based
    """
    path = Path(path)
    suffix = _mesh_suffix(path)
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    cells = np.column_stack([np.full(len(faces), 3), faces])  # vertex count, then indices
    with atomic_write(path) as tmp:
        if suffix == ".off":
            with open(tmp, "w", encoding="ascii") as fh:
                fh.write(f"OFF\n{len(vertices)} {len(faces)} 0\n")
                np.savetxt(fh, vertices, fmt="%.9g")
                np.savetxt(fh, cells, fmt="%d")
        else:
            pv.PolyData(vertices, cells.ravel()).save(str(tmp))
