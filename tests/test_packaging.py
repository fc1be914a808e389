"""What ``pip install`` puts on the path: everything under ``medseg``, nothing generic.

The stage folders ``training/``, ``inference/`` and ``evaluation/`` sit at the repository's
top level but install as ``medseg.training``, ``medseg.inference`` and ``medseg.evaluation``
(``pyproject.toml``'s ``package-dir``), so that medseg cannot break, or be broken by, another
project's module of one of those names.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import tomllib

REPO = Path(__file__).resolve().parents[1]
STAGES = ("training", "inference", "evaluation")


def _tree_packages() -> set[str]:
    """Every package folder of the repository, by the name it installs under."""
    found = set()
    for root, prefix in [("medseg", "medseg"), *[(s, f"medseg.{s}") for s in STAGES]]:
        for init in (REPO / root).rglob("__init__.py"):
            parts = init.parent.relative_to(REPO / root).parts
            found.add(".".join((prefix, *parts)))
    return found


def _pyproject() -> dict:
    with open(REPO / "pyproject.toml", "rb") as fh:
        return tomllib.load(fh)


def test_the_package_list_names_every_package_folder():
    listed = set(_pyproject()["tool"]["setuptools"]["packages"])
    assert listed == _tree_packages()


def test_console_scripts_point_inside_medseg():
    scripts = _pyproject()["project"]["scripts"]
    assert set(scripts) == {
        "medseg-train", "medseg-segment", "medseg-evaluate", "medseg-match", "medseg-demo",
    }  # fmt: skip
    assert all(target.startswith("medseg.") for target in scripts.values())


def test_installed_names_resolve_under_medseg_only(tmp_path):
    # outside the repository, so that its top-level folders are not on the path
    code = (
        "import importlib.util as u, medseg.evaluation, medseg.training.cli, "
        "medseg.inference.cli, medseg.inference.match_cli, medseg.evaluation.baselines; "
        f"print([n for n in {STAGES!r} if u.find_spec(n) is not None])"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[]"


@pytest.mark.slow
def test_the_wheel_holds_medseg_and_nothing_else(tmp_path):
    # built from a copy: setuptools writes build/ and *.egg-info/ into the source folder
    source = tmp_path / "source"
    shutil.copytree(REPO, source, ignore=shutil.ignore_patterns(
        ".git", "build", "dist", "*.egg-info", "__pycache__", ".*_cache", "medseg-demo",
    ))  # fmt: skip
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation",
         "--quiet", "-w", str(tmp_path)],
        check=True, capture_output=True, cwd=tmp_path,
    )  # fmt: skip
    (wheel,) = tmp_path.glob("medseg-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {name.split("/")[0] for name in names}
    assert {t for t in top if not t.endswith(".dist-info")} == {"medseg"}
    modules = {name for name in names if name.endswith(".py")}
    expected = {
        f"medseg/{p.relative_to(REPO / 'medseg').as_posix()}"
        for p in (REPO / "medseg").rglob("*.py")
    }
    for stage in STAGES:
        expected |= {
            f"medseg/{stage}/{p.relative_to(REPO / stage).as_posix()}"
            for p in (REPO / stage).rglob("*.py")
        }
    assert modules == expected
