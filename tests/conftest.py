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
#: Set (to anything but empty or 0) where the real data must be present, as in CI
#: (``.ci/run``): a missing data folder then fails the tests that need it instead of
#: skipping them, so a CI run without the data cannot pass.
REQUIRE_DATA = os.environ.get("MEDSEG_REQUIRE_DATA", "") not in ("", "0")
_DATA_FIXTURES = {"data_root", "hippocampus_dir", "shapes_dir"}


def _data_root() -> Path:
    env = os.environ.get("MEDSEG_DATA")
    return Path(env) if env else REPO_ROOT.parent / "shared" / "data"


def _missing(reason: str) -> None:
    if REQUIRE_DATA:
        pytest.fail(f"{reason} (MEDSEG_REQUIRE_DATA is set, so this is a failure)")
    pytest.skip(reason)


def pytest_collection_modifyitems(config, items):
    """Every test that uses the real data must carry the ``data`` mark (``-m "not data"``
    then really leaves the data out); an unmarked one is a collection error."""
    unmarked = [
        item.nodeid
        for item in items
        if _DATA_FIXTURES & set(getattr(item, "fixturenames", ()))
        and item.get_closest_marker("data") is None
    ]
    if unmarked:
        raise pytest.UsageError(
            "tests using the real data lack @pytest.mark.data: " + ", ".join(unmarked)
        )


@pytest.fixture(scope="session")
def data_root() -> Path:
    """Root of the real data (``MEDSEG_DATA`` or ``../shared/data``); skips if absent."""
    root = _data_root()
    if not root.is_dir():
        _missing(
            f"real data not found at {root}: set MEDSEG_DATA to the folder holding "
            "hippocampus/ and shapes/ to run this test"
        )
    return root


@pytest.fixture(scope="session")
def hippocampus_dir(data_root: Path) -> Path:
    path = data_root / "hippocampus"
    if not (path / "dataset.json").is_file():
        _missing(f"hippocampus cohort not found at {path}")
    return path


@pytest.fixture(scope="session")
def shapes_dir(data_root: Path) -> Path:
    path = data_root / "shapes"
    if not path.is_dir():
        _missing(f"FAUST / TOSCA meshes not found at {path}")
    return path
