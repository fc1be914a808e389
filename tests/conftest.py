"""Shared fixtures: where the real data lives, and small generated inputs."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

# CI must be reproducible: the same examples every run (a failure there is a real change,
# not a new random draw). Locally, hypothesis keeps exploring new examples.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

REPO_ROOT = Path(__file__).resolve().parents[1]


def _data_root() -> Path:
    env = os.environ.get("MEDSEG_DATA")
    return Path(env) if env else REPO_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def data_root() -> Path:
    """Root of the real data (``MEDSEG_DATA`` or ``../shared/data``); skips if absent."""
    root = _data_root()
    if not root.is_dir():
        pytest.skip(
            f"real data not found at {root}: set MEDSEG_DATA to the folder holding "
            "hippocampus/ and shapes/ to run this test"
        )
    return root


@pytest.fixture(scope="session")
def hippocampus_dir(data_root: Path) -> Path:
    path = data_root / "hippocampus"
    if not (path / "dataset.json").is_file():
        pytest.skip(f"hippocampus cohort not found at {path}")
    return path


@pytest.fixture(scope="session")
def shapes_dir(data_root: Path) -> Path:
    path = data_root / "shapes"
    if not path.is_dir():
        pytest.skip(f"FAUST / TOSCA meshes not found at {path}")
    return path
