"""The command-line tools as a user meets them: a fast ``--help``, and ``medseg-segment --jobs``.

* Every console script builds its parser, answers ``--help`` and reports an argument error
  without importing the heavy libraries (checked in a fresh interpreter's ``sys.modules``);
* ``medseg-train``'s defaults, written out so that its parser needs no segmenter, are the
  model's own;
* ``medseg-segment --jobs N`` on a folder writes the same label maps as ``--jobs 1``, skips
  a bad file the same way, and caps the workers to the memory limit.
"""

from __future__ import annotations

import inspect
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from test_bad_inputs import _tiny

from medseg.inference.cli import main as segment_main
from medseg.io import read_image
from medseg.memory import ENV_VAR
from medseg.segmenter import ShapePriorSegmenter, load_model, segment_bytes

REPO = Path(__file__).resolve().parents[1]
CLI_MODULES = (
    "medseg.inference.cli",
    "medseg.inference.match_cli",
    "medseg.training.cli",
    "medseg.evaluation.cli",
    "medseg.evaluation.demo",
)
#: What the tools must not import before they work (each costs from a tenth of a second,
#: numpy, to seconds, scikit-learn and pyvista / VTK).
HEAVY = (
    "numpy",
    "scipy",
    "sklearn",
    "skimage",
    "SimpleITK",
    "nibabel",
    "pyvista",
    "vtk",
    "vtkmodules",
    "skops",
    "joblib",
    "matplotlib",
    "potpourri3d",
    "tqdm",
    "medseg.segmenter",
)

_PROBE = """
import contextlib, io, json, sys
from importlib import import_module
cli = import_module(sys.argv[1])
outcome = {}
for argv in (["--help"], ["--no-such-option"]):
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            cli.main(argv)
        except SystemExit as exc:
            outcome[argv[0]] = exc.code
heavy = json.loads(sys.argv[2])
outcome["loaded"] = sorted(m for m in sys.modules if m in heavy or m.split(".")[0] in heavy)
print(json.dumps(outcome))
"""


@pytest.mark.parametrize("module", CLI_MODULES)
def test_help_and_usage_errors_import_no_heavy_module(module):
    """A top-level import of the segmenter (or numpy, SimpleITK, ...) in a CLI fails this."""
    done = subprocess.run(
        [sys.executable, "-c", _PROBE, module, json.dumps(HEAVY)],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    outcome = json.loads(done.stdout)
    assert outcome["--help"] == 0 and outcome["--no-such-option"] == 2, outcome
    assert outcome["loaded"] == [], f"{module} imports {outcome['loaded']} before its work"


def test_train_cli_defaults_are_the_models():
    from medseg.training.cli import _DEFAULT

    signature = inspect.signature(ShapePriorSegmenter).parameters
    assert _DEFAULT == {name: signature[name].default for name in _DEFAULT}


# ----------------------------------------------------------------------------- --jobs


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> tuple[Path, Path]:
    """``(model, input folder)``: the tiny model of test_bad_inputs.py, 3 images, 1 corrupt."""
    model, data = _tiny(tmp_path_factory.getbasetemp())
    inputs = tmp_path_factory.mktemp("jobs") / "inputs"
    inputs.mkdir()
    for source in sorted((data / "imagesTr").iterdir())[:3]:
        shutil.copy(source, inputs / source.name)
    (inputs / "broken_0000.nii.gz").write_bytes(b"not a nifti file")
    return model, inputs


def _segment(model: Path, inputs: Path, out: Path, jobs: str, capfd) -> tuple[int, str, str]:
    code = segment_main(["-m", str(model), "-i", str(inputs), "-o", str(out), "--jobs", jobs])
    captured = capfd.readouterr()
    return code, captured.out, captured.err


def test_jobs_2_writes_what_jobs_1_writes_and_skips_the_same_bad_file(folder, tmp_path, capfd):
    model, inputs = folder
    one = _segment(model, inputs, tmp_path / "one", "1", capfd)
    two = _segment(model, inputs, tmp_path / "two", "2", capfd)
    written = sorted(p.name for p in (tmp_path / "one").iterdir())
    names = [n for n in written if n.endswith(".nii.gz")]
    assert len(names) == 3 and "broken.nii.gz" not in names
    # beside each label map its quality record (JSON), the same from both runs
    assert written == sorted(names + [n.replace(".nii.gz", ".quality.json") for n in names])
    assert sorted(p.name for p in (tmp_path / "two").iterdir()) == written  # nor temporaries
    for name in written:
        if name.endswith(".json"):
            assert (tmp_path / "one" / name).read_text() == (tmp_path / "two" / name).read_text()
    for name in names:
        a, b = read_image(tmp_path / "one" / name), read_image(tmp_path / "two" / name)
        assert a.GetSize() == b.GetSize() and a.GetOrigin() == b.GetOrigin()
        assert a.GetSpacing() == b.GetSpacing() and a.GetDirection() == b.GetDirection()
        np.testing.assert_array_equal(sitk.GetArrayFromImage(a), sitk.GetArrayFromImage(b))
    for code, _, err in (one, two):
        assert code == 1, err
        assert "Traceback" not in err
        assert "medseg-segment: skipped broken_0000.nii.gz: " in err
        assert "medseg-segment: 1 of 4 images failed" in err
    # the printed lines keep the input order, whatever order the workers finish in
    lines = [out.splitlines() for _, out, _ in (one, two)]
    assert [line.split(" -> ")[0] for line in lines[1]] == [
        line.split(" -> ")[0] for line in lines[0]
    ]
    assert len(lines[1]) == 3
    assert "in 2 worker processes, 1 forest thread each" in two[2]


def test_jobs_are_capped_to_the_memory_limit(folder, tmp_path, capfd, monkeypatch):
    model_dir, inputs = folder
    model = load_model(model_dir)
    image = read_image(next(inputs.glob("phantom*")))
    peak = segment_bytes(model, image.GetSize(), image.GetSpacing())
    monkeypatch.setenv(ENV_VAR, repr(1.5 * peak / 2**30))  # one image fits, two do not
    code, out, err = _segment(model_dir, inputs, tmp_path / "out", "2", capfd)
    assert code == 1, err
    assert "--jobs 2 capped to 1: one image needs about" in err
    assert "worker processes" not in err  # one worker: in this process
    assert len(out.splitlines()) == 3


@pytest.mark.parametrize("value", ["0", "-2", "two"])
def test_jobs_below_one_is_a_usage_error(value, folder, tmp_path, capfd):
    model, inputs = folder
    with pytest.raises(SystemExit) as info:
        segment_main(["-m", str(model), "-i", str(inputs), "-o", str(tmp_path), "--jobs", value])
    err = capfd.readouterr().err
    assert info.value.code == 2
    assert "Traceback" not in err
    lines = err.strip().splitlines()  # argparse's usage, then its one error line
    assert lines[0].startswith("usage: medseg-segment")
    assert [line for line in lines if "error" in line] == [lines[-1]]
    assert lines[-1].startswith("medseg-segment: error: argument --jobs: ")
    assert not any(tmp_path.iterdir())


def test_no_appearance_check_keeps_the_mrf_shape_and_the_record_says_what_the_check_saw(
    folder, tmp_path, capfd
):
    model_path, inputs = folder
    source = sorted(inputs.glob("phantom_*"))[1]
    model = load_model(model_path)
    assert model.appearance_check and model.appearance_ is not None  # on by default
    out = tmp_path / "checked.nii.gz"
    assert segment_main(["-m", str(model_path), "-i", str(source), "-o", str(out)]) == 0
    record = json.loads((tmp_path / "checked.quality.json").read_text())
    seen = model.segment(source).appearance
    assert record["appearance"]["score"] == pytest.approx(seen["score"])
    assert record["appearance"]["searched"] == (seen["score"] < seen["threshold"])
    capfd.readouterr()
    assert segment_main(["-m", str(model_path), "-i", str(source), "-o",
                         str(tmp_path / "plain.nii.gz"), "--no-appearance-check"]) == 0  # fmt: skip
    model.appearance_check = False
    written = sitk.GetArrayFromImage(read_image(tmp_path / "plain.nii.gz"))
    np.testing.assert_array_equal(written, sitk.GetArrayFromImage(model.segment(source).label))
    assert json.loads((tmp_path / "plain.quality.json").read_text())["appearance"] is None


def test_no_boundary_writes_the_shape_only_map_and_no_quality_record(folder, tmp_path, capfd):
    model_path, inputs = folder
    source = sorted(inputs.glob("phantom_*"))[0]
    code = segment_main(["-m", str(model_path), "-i", str(source), "-o",
                         str(tmp_path / "plain.nii.gz"), "--no-boundary"])  # fmt: skip
    assert code == 0, capfd.readouterr().err
    model = load_model(model_path)
    seg = model.segment(source)
    written = sitk.GetArrayFromImage(read_image(tmp_path / "plain.nii.gz"))
    np.testing.assert_array_equal(written, sitk.GetArrayFromImage(seg.shape_label))
    assert not (tmp_path / "plain.quality.json").exists()
    assert segment_main(["-m", str(model_path), "-i", str(source), "-o",
                         str(tmp_path / "refined.nii.gz")]) == 0  # fmt: skip
    refined = sitk.GetArrayFromImage(read_image(tmp_path / "refined.nii.gz"))
    np.testing.assert_array_equal(refined, sitk.GetArrayFromImage(seg.label))
    record = json.loads((tmp_path / "refined.quality.json").read_text())
    assert set(record) >= {"score", "flagged", "disagreement", "change", "mrf_gap"}
