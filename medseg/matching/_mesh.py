"""Triangle meshes in and out, and the checks a mesh must pass before it is matched.

A mesh is a pair of plain arrays: ``vertices`` (V, 3) float (x, y, z) and ``faces`` (F, 3)
int, 0-based. Files are read and written with pyvista (PLY, OBJ, STL, VTK, VTP) and with a
small built-in reader/writer for OFF, which pyvista cannot read without meshio.
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
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from medseg.errors import InputFileError, MeshError
from medseg.io import atomic_write

__all__ = ["read_mesh", "write_mesh", "check_mesh", "MESH_SUFFIXES"]

MESH_SUFFIXES = (".off", ".ply", ".obj", ".stl", ".vtk", ".vtp")


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
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshError(
            f"{path}: unsupported mesh format {suffix!r}; use one of {', '.join(MESH_SUFFIXES)}."
        )
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
    bad = ~np.all(np.isfinite(vertices), axis=1)
    if bad.any():
        raise MeshError(
            f"{path}: {int(bad.sum())} vertices have NaN or infinite coordinates (first: vertex "
            f"{int(np.flatnonzero(bad)[0])}); fix or re-export the mesh."
        )
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(
            f"{path}: face indices must lie in [0, {len(vertices) - 1}] (0-based, "
            f"{len(vertices)} vertices), got range [{faces.min()}, {faces.max()}]; the file is "
            "corrupt: re-export the mesh."
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
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshError(
            f"{path}: unsupported mesh format {suffix!r}; use one of {', '.join(MESH_SUFFIXES)}."
        )
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    with atomic_write(path) as tmp:
        if suffix == ".off":
            with open(tmp, "w", encoding="ascii") as fh:
                fh.write(f"OFF\n{len(vertices)} {len(faces)} 0\n")
                np.savetxt(fh, vertices, fmt="%.9g")
                np.savetxt(fh, np.column_stack([np.full(len(faces), 3), faces]), fmt="%d")
        else:
            cells = np.column_stack([np.full(len(faces), 3), faces]).ravel()
            pv.PolyData(vertices, cells).save(str(tmp))


def _edges(faces: np.ndarray) -> np.ndarray:
    """Directed half-edges (3F, 2) in face order: (0,1), (1,2), (2,0) of each face."""
    return faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)


def check_mesh(
    vertices: ArrayLike,
    faces: ArrayLike,
    *,
    name: str = "mesh",
    allow_boundary: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Check that a mesh can be matched; return it with outward-oriented faces.

    The matcher needs a connected, edge-manifold, consistently oriented triangle mesh of genus
    0: a closed sphere-like surface, or one with holes (boundary loops), which the conformal
    flattening closes with a fan per loop.

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (F, 3) int array, 0-based
    name : str
        How the mesh is named in error messages (e.g. its file name).
    allow_boundary : bool
        Accept meshes with boundary loops (genus 0 with holes). Default True.

    Returns
    -------
    vertices : (V, 3) float array
        Unchanged (a float copy).
    faces : (F, 3) int64 array
        The same triangles; on a closed mesh whose normals point inwards (negative enclosed
        volume) every face is reversed so normals point outwards. This is the only repair:
        vertex indices, hence the output map, never change.

    Raises
    ------
    MeshError
        Non-finite vertices, face indices out of range, degenerate faces (repeated vertex or
        zero area), unreferenced vertices, non-manifold edges, inconsistent orientation, more
        than one connected component, or a genus other than 0; the message says which, how
        many, and what to do.
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4:
        raise MeshError(f"{name}: vertices must be a (V, 3) array with V >= 4, got {v.shape}.")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) < 4:
        raise MeshError(f"{name}: faces must be an (F, 3) array with F >= 4, got {f.shape}.")
    if not np.issubdtype(f.dtype, np.integer):
        if not np.all(np.isfinite(f)) or np.any(f != np.round(f)):
            raise MeshError(f"{name}: face indices must be integers.")
    f = f.astype(np.int64)
    bad = ~np.all(np.isfinite(v), axis=1)
    if bad.any():
        raise MeshError(
            f"{name}: {bad.sum()} vertices have NaN or infinite coordinates "
            f"(first: {np.flatnonzero(bad)[0]}); fix or remove them."
        )
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(
            f"{name}: face indices must lie in [0, {len(v) - 1}] (0-based), "
            f"got range [{f.min()}, {f.max()}]."
        )
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    scale = np.ptp(v, axis=0).max() or 1.0
    degenerate = repeated | (area <= 1e-12 * scale**2)
    if degenerate.any():
        raise MeshError(
            f"{name}: {degenerate.sum()} degenerate faces (repeated vertex or zero area; first: "
            f"face {np.flatnonzero(degenerate)[0]}); remove them, e.g. with "
            "pyvista's clean() or a remeshing tool."
        )
    used = np.zeros(len(v), dtype=bool)
    used[f.ravel()] = True
    if not used.all():
        raise MeshError(
            f"{name}: {(~used).sum()} vertices belong to no face (first: "
            f"{np.flatnonzero(~used)[0]}); remove unreferenced vertices."
        )
    half = _edges(f)
    und = np.sort(half, axis=1)
    key = und[:, 0] * len(v) + und[:, 1]
    uniq, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    if (counts > 2).any():
        raise MeshError(
            f"{name}: {(counts > 2).sum()} non-manifold edges (shared by more than two faces); "
            "the matcher needs a manifold surface."
        )
    dkey = half[:, 0] * len(v) + half[:, 1]
    if len(np.unique(dkey)) != len(dkey):
        raise MeshError(
            f"{name}: faces are not consistently oriented (an edge is traversed twice in the "
            "same direction); reorient the faces (e.g. pyvista's compute_normals("
            "consistent_normals=True))."
        )
    n_comp, _ = connected_components(
        coo_matrix((np.ones(len(half)), (half[:, 0], half[:, 1])), shape=(len(v), len(v))),
        directed=False,
    )
    if n_comp != 1:
        raise MeshError(
            f"{name}: mesh has {n_comp} connected components; match one surface at a time "
            "(keep the largest component, e.g. pyvista's connectivity('largest'))."
        )
    n_edges = len(uniq)
    n_boundary_edges = int((counts == 1).sum())
    n_loops = _count_boundary_loops(half, counts[inverse] == 1, len(v))
    euler = len(v) - n_edges + len(f)
    genus2 = 2 - euler - n_loops
    if genus2 != 0:
        raise MeshError(
            f"{name}: surface has genus {genus2 / 2:g} (Euler characteristic {euler}, "
            f"{n_loops} boundary loops); the matcher needs a genus-0 surface (sphere-like, "
            "possibly with holes): close handles or tunnels first."
        )
    if n_boundary_edges and not allow_boundary:
        raise MeshError(f"{name}: surface has {n_loops} holes; a closed surface is required.")
    if n_boundary_edges == 0:
        p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        volume = np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum() / 6.0
        if volume < 0:
            f = f[:, ::-1].copy()
    return v.copy(), f


def _count_boundary_loops(half: np.ndarray, is_boundary: np.ndarray, n_vertices: int) -> int:
    """Number of boundary loops, from the boundary half-edges' connectivity."""
    b = half[is_boundary]
    if len(b) == 0:
        return 0
    graph = coo_matrix((np.ones(len(b)), (b[:, 0], b[:, 1])), shape=(n_vertices, n_vertices))
    _, labels = connected_components(graph, directed=False)
    return len(np.unique(labels[np.unique(b.ravel())]))
