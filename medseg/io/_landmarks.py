"""Landmark files: CSV (x, y, z in mm, LPS), 3D Slicer ``.fcsv`` and ``.mrk.json``.

Points are returned and taken as ``(N, 3)`` float arrays in millimetres, ``(x, y, z)``, in
ITK's LPS world frame. Slicer stores RAS or LPS per file; the file's own declaration is
honoured on reading (x and y negated for RAS) and LPS is written.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from medseg.errors import InputFileError, LandmarkFileError, ParameterError
from medseg.io._atomic import PathLike, atomic_write

__all__ = ["LANDMARK_SUFFIXES", "read_landmarks", "write_landmarks"]

LANDMARK_SUFFIXES = (".csv", ".fcsv", ".mrk.json")

_RAS_LPS = np.array([-1.0, -1.0, 1.0])
_FCSV_COLUMNS = "id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID".split(",")
_MRK_SCHEMA = (
    "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
    "Resources/Schema/markups-schema-v1.0.3.json#"
)


def _landmark_suffix(path: Path) -> str:
    name = path.name.lower()
    for suffix in LANDMARK_SUFFIXES:
        if name.endswith(suffix):
            return suffix
    return path.suffix


def _error(path: Path, line: int | None, message: str) -> LandmarkFileError:
    where = f"{str(path)!r}" + (f", line {line}" if line is not None else "")
    return LandmarkFileError(f"{where}: {message}")


def _parse_xyz(path: Path, line: int, values: Sequence[str]) -> list[float]:
    try:
        xyz = [float(v) for v in values]
    except ValueError:
        raise _error(path, line, f"non-numeric coordinate in {list(values)}") from None
    if not np.all(np.isfinite(xyz)):
        raise _error(path, line, f"non-finite coordinate in {list(values)}")
    return xyz


# --------------------------------------------------------------------------- reading


def _read_csv(path: Path, text: str) -> tuple[np.ndarray, list[str]]:
    reader = csv.reader(io.StringIO(text))
    rows = [(reader.line_num, row) for row in reader if any(c.strip() for c in row)]
    if not rows:
        raise _error(path, None, "empty file; expected a header x,y,z and one row per point")
    header_line, header = rows[0]
    columns = [c.strip().lower() for c in header]
    missing = [c for c in ("x", "y", "z") if c not in columns]
    if missing:
        raise _error(
            path,
            header_line,
            f"header {header} lacks column(s) {missing}; the first line must name the "
            "columns x,y,z (mm, LPS) and optionally label",
        )
    ix = [columns.index(c) for c in ("x", "y", "z")]
    il = columns.index("label") if "label" in columns else None
    points, labels = [], []
    for line, row in rows[1:]:
        if len(row) != len(header):
            raise _error(path, line, f"{len(row)} fields, the header has {len(header)} ({header})")
        points.append(_parse_xyz(path, line, [row[i] for i in ix]))
        labels.append(row[il].strip() if il is not None else str(len(labels)))
    return np.asarray(points, dtype=float).reshape(-1, 3), labels


def _fcsv_system(path: Path, line: int, value: str) -> str:
    value = value.strip().upper()
    if value in ("RAS", "0"):
        return "RAS"
    if value in ("LPS", "1"):
        return "LPS"
    raise _error(
        path,
        line,
        f"unsupported CoordinateSystem {value!r}; only RAS (0) and LPS (1) are supported "
        "(IJK points need their image: export them in world coordinates from Slicer)",
    )


def _read_fcsv(path: Path, text: str) -> tuple[np.ndarray, list[str]]:
    system = "RAS"  # Slicer files written before the header existed are RAS
    columns = list(_FCSV_COLUMNS)
    points, labels = [], []
    for line, raw in enumerate(text.splitlines(), start=1):
        if not raw.strip():
            continue
        if raw.startswith("#"):
            key, _, value = raw[1:].partition("=")
            key = key.strip().lower()
            if key == "coordinatesystem":
                system = _fcsv_system(path, line, value)
            elif key == "columns":
                columns = [c.strip().lower() for c in value.split(",")]
                if not {"x", "y", "z"} <= set(columns):
                    raise _error(path, line, f"columns header {value.strip()!r} lacks x,y,z")
            continue
        row = next(csv.reader([raw]))
        ix = [columns.index(c) for c in ("x", "y", "z")]
        if len(row) <= max(ix):
            raise _error(path, line, f"{len(row)} fields, expected at least {max(ix) + 1}")
        points.append(_parse_xyz(path, line, [row[i] for i in ix]))
        il = columns.index("label") if "label" in columns else None
        labels.append(row[il] if il is not None and il < len(row) else str(len(labels)))
    if not points:
        raise _error(path, None, "no control points in the file")
    xyz = np.asarray(points, dtype=float).reshape(-1, 3)
    return (xyz * _RAS_LPS if system == "RAS" else xyz), labels


def _json_line(text: str, needle: str, start: int = 0) -> int | None:
    index = text.find(needle, start)
    return text.count("\n", 0, index) + 1 if index >= 0 else None


def _read_mrk_json(path: Path, text: str) -> tuple[np.ndarray, list[str]]:
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise _error(path, exc.lineno, f"not valid JSON: {exc.msg}") from None
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(markups, list) or not markups:
        raise _error(path, None, "no 'markups' list: not a 3D Slicer markups file")
    points, labels = [], []
    search_from = 0
    for m, markup in enumerate(markups):
        if not isinstance(markup, dict) or not isinstance(markup.get("controlPoints", []), list):
            raise _error(path, None, f"markup {m} is not a markups object with controlPoints")
        system = str(markup.get("coordinateSystem", "LPS")).upper()  # schema default: LPS
        if system not in ("LPS", "RAS"):
            raise _error(
                path,
                _json_line(text, "coordinateSystem"),
                f"markup {m}: coordinateSystem {system!r} is not RAS or LPS",
            )
        units = markup.get("coordinateUnits", "mm")
        units = units[0] if isinstance(units, list) and units else units
        scale = {"mm": 1.0, "um": 1e-3}.get(units)
        if scale is None:
            raise _error(path, None, f"markup {m}: coordinateUnits {units!r} not mm or um")
        flip = _RAS_LPS if system == "RAS" else np.ones(3)
        for p, point in enumerate(markup.get("controlPoints", [])):
            line = _json_line(text, '"position"', search_from)
            search_from = text.find('"position"', search_from) + 1
            if not isinstance(point, dict):
                raise _error(path, line, f"markup {m}, control point {p} is not an object")
            status = point.get("positionStatus", "defined")
            position = point.get("position")
            if status not in ("defined", "preview") or position is None:
                raise _error(
                    path,
                    line,
                    f"markup {m}, control point {p} ({point.get('label', '')!r}) has no "
                    f"position (status {status!r}); place it or delete it in Slicer",
                )
            if not isinstance(position, list) or len(position) != 3:
                raise _error(
                    path, line, f"control point {p}: position {position!r} is not 3 numbers"
                )
            try:
                xyz = _parse_xyz(path, line, position)
            except TypeError:
                raise _error(path, line, f"non-numeric position {position!r}") from None
            points.append(np.asarray(xyz) * flip * scale)
            labels.append(str(point.get("label", p)))
    if not points:
        raise _error(path, None, "no control points in the file")
    return np.asarray(points, dtype=float).reshape(-1, 3), labels


def read_landmarks(
    path: PathLike, *, n_landmarks: int | None = None, return_labels: bool = False
) -> np.ndarray | tuple[np.ndarray, list[str]]:
    """Read landmark points from a CSV, Slicer ``.fcsv`` or Slicer ``.mrk.json`` file.

    Parameters
    ----------
    path : path-like
        * ``.csv``: a header naming columns ``x,y,z`` (mm, LPS; any order, other columns
          ignored) and optionally ``label``, then one row per point;
        * ``.fcsv``: 3D Slicer fiducial list; ``# CoordinateSystem = RAS | LPS | 0 | 1``
          honoured (RAS when absent, as in old files), ``# columns =`` honoured;
        * ``.mrk.json``: 3D Slicer markups; each markup's ``coordinateSystem`` (default
          LPS) and ``coordinateUnits`` (mm or um) honoured; all control points of all
          markups, in file order.
    n_landmarks : int, optional
        Expected number of points; a different count raises.
    return_labels : bool
        Also return the point labels.

    Returns
    -------
    points : (N, 3) float array, mm, (x, y, z), LPS
    labels : list of str, only if ``return_labels``
        The ``label`` column / Slicer labels (``"0"``, ``"1"``, ... if the file has none).

    Raises
    ------
    InputFileError
        The file does not exist.
    LandmarkFileError
        Unknown suffix, missing columns, wrong field count, non-numeric or non-finite
        coordinates, unsupported coordinate system, unplaced points, wrong number of points;
        the message names the file and the line.
    """
    path = Path(path)
    suffix = _landmark_suffix(path)
    readers = {".csv": _read_csv, ".fcsv": _read_fcsv, ".mrk.json": _read_mrk_json}
    if suffix not in readers:
        raise LandmarkFileError(
            f"{str(path)!r}: unknown landmark format {suffix or '(no suffix)'!r}; supported: "
            f"{', '.join(LANDMARK_SUFFIXES)}"
        )
    if not path.is_file():
        raise InputFileError(f"{str(path)!r}: no such landmark file")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise LandmarkFileError(f"{str(path)!r}: cannot read as text: {exc}") from exc
    points, labels = readers[suffix](path, text)
    if n_landmarks is not None and len(points) != n_landmarks:
        raise _error(path, None, f"{len(points)} points, expected {n_landmarks}")
    return (points, labels) if return_labels else points


# --------------------------------------------------------------------------- writing


def _check_points(points: ArrayLike) -> np.ndarray:
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ParameterError(f"`points` must have shape (N, 3) (mm, x-y-z), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ParameterError("`points` must be finite")
    return points


def _format(values: Iterable[float]) -> list[str]:
    return [repr(float(v)) for v in values]  # shortest text that reads back exactly


def write_landmarks(
    points: ArrayLike,
    path: PathLike,
    *,
    labels: Sequence[str] | None = None,
    protect: Iterable[PathLike] = (),
) -> Path:
    """Write landmark points atomically, in LPS millimetres.

    Parameters
    ----------
    points : (N, 3) float array, mm, (x, y, z), LPS
    path : path-like
        ``.csv`` (header ``label,x,y,z``), ``.fcsv`` (Slicer 4.11+ header with
        ``# CoordinateSystem = LPS``) or ``.mrk.json`` (one Fiducial markup with
        ``"coordinateSystem": "LPS"``). Values are written with full float precision, so
        reading gives back the same numbers.
    labels : sequence of str, optional
        One label per point; default ``"0"``, ``"1"``, ...
    protect : iterable of path-like
        Input files that must not be overwritten.

    Returns
    -------
    path : pathlib.Path
    """
    path = Path(path)
    points = _check_points(points)
    labels = [str(i) for i in range(len(points))] if labels is None else [str(s) for s in labels]
    if len(labels) != len(points):
        raise ParameterError(f"{len(labels)} labels for {len(points)} points")
    suffix = _landmark_suffix(path)
    if suffix == ".csv":
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow(["label", "x", "y", "z"])
        writer.writerows([lab, *_format(p)] for lab, p in zip(labels, points, strict=True))
        text = buffer.getvalue()
    elif suffix == ".fcsv":
        buffer = io.StringIO()
        buffer.write("# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\n")
        buffer.write("# columns = " + ",".join(_FCSV_COLUMNS) + "\n")
        writer = csv.writer(buffer, lineterminator="\n")
        for i, (lab, p) in enumerate(zip(labels, points, strict=True)):
            writer.writerow([i + 1, *_format(p), 0, 0, 0, 1, 1, 1, 0, lab, "", ""])
        text = buffer.getvalue()
    elif suffix == ".mrk.json":
        doc = {
            "@schema": _MRK_SCHEMA,
            "markups": [
                {
                    "type": "Fiducial",
                    "coordinateSystem": "LPS",
                    "coordinateUnits": "mm",
                    "controlPoints": [
                        {
                            "id": str(i + 1),
                            "label": lab,
                            "position": [float(v) for v in p],
                            "positionStatus": "defined",
                        }
                        for i, (lab, p) in enumerate(zip(labels, points, strict=True))
                    ],
                }
            ],
        }
        text = json.dumps(doc, indent=2) + "\n"
    else:
        raise LandmarkFileError(
            f"{str(path)!r}: unknown landmark format {suffix or '(no suffix)'!r}; supported: "
            f"{', '.join(LANDMARK_SUFFIXES)}"
        )
    with atomic_write(path, protect=protect) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path
