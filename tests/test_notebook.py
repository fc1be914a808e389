"""The quickstart notebook runs from top to bottom on the phantom (small sizes).

Executed with nbclient in a fresh kernel, as a user would run it, with
``MEDSEG_NOTEBOOK_FAST=1`` (a smoke-test size) and its work folder in ``tmp_path``; the
committed notebook has no outputs.
"""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

import nbformat
import pytest

REPO = Path(__file__).resolve().parents[1]
NOTEBOOK = REPO / "docs" / "notebooks" / "quickstart.ipynb"


def test_notebook_is_committed_without_outputs():
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(nb)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(not c.outputs and c.execution_count is None for c in code)


def _text(cell) -> str:
    return "".join(o.get("text", "") for o in cell.outputs if o.output_type == "stream")


def _images(cell) -> int:
    return sum("image/png" in o.get("data", {}) for o in cell.outputs)


def test_quickstart_runs_on_the_phantom(tmp_path, monkeypatch):
    from nbclient import NotebookClient

    monkeypatch.setenv("MEDSEG_NOTEBOOK_FAST", "1")
    monkeypatch.setenv("MEDSEG_NOTEBOOK_WORKDIR", str(tmp_path / "work"))
    monkeypatch.setenv("MEDSEG_NOTEBOOK_DATASET", "phantom")
    monkeypatch.setenv("PYVISTA_OFF_SCREEN", "true")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    # the kernel imports the checkout under test, whatever is installed
    monkeypatch.setenv(
        "PYTHONPATH", os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p)
    )
    monkeypatch.delenv("MPLBACKEND", raising=False)  # the kernel's inline backend
    nb = nbformat.read(NOTEBOOK, as_version=4)
    client = NotebookClient(
        nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    start = time.perf_counter()
    client.execute()
    seconds = time.perf_counter() - start
    print(f"quickstart notebook executed in {seconds:.1f} s")

    code = [c for c in nb.cells if c.cell_type == "code"]
    errors = [o for c in code for o in c.outputs if o.output_type == "error"]
    assert not errors
    out = "\n".join(_text(c) for c in code)
    assert "dataset: phantom; fast: True" in out
    assert f"work folder: {tmp_path / 'work'}" in out
    # trained, saved, segmented with a certified MRF solution
    assert (tmp_path / "work" / "model").is_dir()
    dice = float(re.search(r": Dice ([0-9.]+), HD95", out).group(1))
    gap = float(re.search(r"MRF gap ([-+0-9.e]+)", out).group(1))
    error = float(re.search(r"landmark error ([0-9.]+) mm \(", out).group(1))
    assert gap >= 0.0
    # the overlay, the 3D view and the cross-validation plot are figures
    assert sum(_images(c) for c in code) >= 3
    # every case scored once by each method, in subject-grouped folds
    cv = {}
    for method in ("detection", "shape_prior"):
        match = re.search(
            rf"{method}: (\d+) cases, mean Dice ([0-9.]+), mean landmark error ([0-9.]+) mm", out
        )
        assert match and int(match.group(1)) == 11
        cv[method] = float(match.group(2)), float(match.group(3))
    assert (tmp_path / "work" / "crossval" / "cases.csv").is_file()
    # What these sizes measure (phantom, FAST, seed 0): the held-out case phantom_010 has
    # Dice 0.471, landmark error 13.40 mm, MRF gap 7.6e-04; the 2-fold cross-validation of
    # the 11 cases has mean Dice 0.509 (shape_prior) and 0.292 (detection), mean landmark
    # error 11.99 and 12.69 mm. One case is one draw: other fits (more trees, candidates or
    # training cases) gave it Dice 0.16 to 0.85, so its bounds are loose. The means over 11
    # cases moved by 0.006 from 6 to 10 candidates: the prior must keep most of its gain.
    # At 8 landmarks, 3 trees and 6 candidates the landmark errors are near chance (the
    # case's landmarks lie 10.6 mm from their centroid, shuffled they are 13.9 mm off): the
    # ceilings catch a wrong frame (an LPS/RAS flip is 19 mm off, voxel indices 43 mm), not
    # a worse detector.
    # One case is one draw of a pipeline whose outcome flips with the last bit of its
    # arithmetic: on an AVX2 machine (2026-12-07) the same fit gave this case 0.284 (14.7 mm),
    # with cross-validation means 0.654 and 0.281. The floor catches a wrong frame (Dice
    # near 0); the means over 11 cases below guard the accuracy.
    assert dice >= 0.15
    assert error <= 16.0
    assert cv["shape_prior"][0] >= 0.42
    assert cv["shape_prior"][0] - cv["detection"][0] >= 0.12
    assert cv["shape_prior"][1] <= 15.0 and cv["detection"][1] <= 15.0
    # nothing written beside the notebook
    assert sorted(p.name for p in NOTEBOOK.parent.iterdir()) == ["quickstart.ipynb"]


@pytest.mark.parametrize("name", ["README.md"])
def test_readme_links_the_notebook(name):
    assert "docs/notebooks/quickstart.ipynb" in (REPO / name).read_text(encoding="utf-8")
