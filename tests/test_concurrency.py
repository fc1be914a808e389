"""Concurrent runs and interrupted runs.

* two ``medseg-segment`` processes writing into one output folder (same inputs, and
  different inputs) leave only complete files, each equal to a serial run's;
* two processes writing the same file name through ``medseg.io`` many times, including a
  format with a companion data file (``.mhd`` + ``.zraw``), never leave a half-written file or
  a header paired with the other writer's data;
* ``run_evaluation`` killed (SIGINT or SIGTERM) once rows are on disk resumes without
  recomputing finished cases and ends with the table of an uninterrupted run (with a
  perturbation condition of the same angle as the unperturbed case, so that rows are told
  apart by the condition's name).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from medseg.datasets import make_phantom_cohort
from medseg.evaluation.results import COLUMNS, read_results
from medseg.inference.cli import main as segment_main
from medseg.io import read_image, read_landmarks, write_image
from medseg.segmenter import ShapePriorSegmenter

REPO = Path(__file__).resolve().parents[1]
SEGMENT = "import sys; from medseg.inference.cli import main; sys.exit(main(sys.argv[1:]))"


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH")) if p)
    env["OMP_NUM_THREADS"] = "1"
    return env


def _python(*args: str) -> list[str]:
    return [sys.executable, *args]


# ----------------------------------------------------------------------------- medseg-segment


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A small saved model, 2 input images, and the serial run's outputs."""
    root = tmp_path_factory.mktemp("concurrency")
    cohort = make_phantom_cohort(8, random_state=3, n_landmarks=8, size=32)
    model = ShapePriorSegmenter(
        n_estimators=3, n_candidates=6, max_iter=50, augment_poses=0, random_state=0
    )  # the file handling is under test: no posed copies (3x the training)
    model.fit(cohort[:6]).save(root / "model")
    inputs = root / "inputs"
    for i, case in enumerate(cohort[6:]):
        write_image(case.load_image(), inputs / f"case{i}_0000.nii.gz")
    serial = root / "serial"
    argv = ["-m", str(root / "model"), "-i", str(inputs), "-o", str(serial), "-q"]
    assert segment_main([*argv, "--save-landmarks", "csv"]) == 0
    return root


def _segment_processes(setup: Path, runs: list[tuple[Path, Path]]) -> None:
    """Start one medseg-segment process per (input, output) at once; all must succeed."""
    procs = [
        subprocess.Popen(
            _python("-c", SEGMENT, "-m", str(setup / "model"), "-i", str(src), "-o", str(dst))
            + ["-q", "--save-landmarks", "csv"],
            env=_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for src, dst in runs
    ]
    for proc in procs:
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err


def _assert_equal_to_serial(folder: Path, serial: Path, names: list[str]) -> None:
    # exactly the expected files: no temporary folder or half-written file left behind
    expected = sorted(f"{n}{ext}" for n in names for ext in (".nii.gz", ".csv", ".quality.json"))
    assert sorted(p.name for p in folder.iterdir()) == expected
    for name in names:
        got = json.loads((folder / f"{name}.quality.json").read_text(encoding="utf-8"))
        assert got == json.loads((serial / f"{name}.quality.json").read_text(encoding="utf-8"))
        got, ref = read_image(folder / f"{name}.nii.gz"), read_image(serial / f"{name}.nii.gz")
        assert got.GetSize() == ref.GetSize() and got.GetOrigin() == ref.GetOrigin()
        assert got.GetSpacing() == ref.GetSpacing() and got.GetDirection() == ref.GetDirection()
        np.testing.assert_array_equal(sitk.GetArrayFromImage(got), sitk.GetArrayFromImage(ref))
        np.testing.assert_array_equal(
            read_landmarks(folder / f"{name}.csv"), read_landmarks(serial / f"{name}.csv")
        )


def test_two_runs_on_the_same_inputs_into_one_folder(setup):
    out = setup / "same"
    _segment_processes(setup, [(setup / "inputs", out), (setup / "inputs", out)])
    _assert_equal_to_serial(out, setup / "serial", ["case0", "case1"])


def test_two_runs_on_different_inputs_into_one_folder(setup):
    halves = [setup / "first", setup / "second"]
    for k, half in enumerate(halves):
        half.mkdir()
        name = f"case{k}_0000.nii.gz"
        os.link(setup / "inputs" / name, half / name)
    out = setup / "mixed"
    _segment_processes(setup, [(halves[0], out), (halves[1], out)])
    _assert_equal_to_serial(out, setup / "serial", ["case0", "case1"])


# ----------------------------------------------------------------------------- atomic writes

WRITER = textwrap.dedent(
    """
    import sys
    import numpy as np
    import SimpleITK as sitk
    from medseg.io import write_image

    value, target, count = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
    # each writer's image has its own value and its own size (so its own header)
    size = 8 + value
    image = sitk.GetImageFromArray(np.full((size, size, size), value, dtype=np.int16))
    for _ in range(count):
        write_image(image, target)
    """
)


def _snapshot(target: Path, copy: Path) -> np.ndarray | None:
    """The voxels of ``target`` as one reader sees them at one moment, or None if absent.

    ITK opens a file twice (header, then data), so reading ``target`` itself while another
    process renames a new file into place may pair the header of one with the data of the
    other. A snapshot copies the file through one open descriptor first: what a single
    open sees, which is what atomic writes promise. A header and its data file (``.mhd`` +
    ``.zraw``) are two files, two renames and two opens: a snapshot of the pair may tear
    (None is returned then; the final pair is checked after the writers finish).
    """
    names = [target] + ([target.with_suffix(".zraw")] if target.suffix == ".mhd" else [])
    try:
        copy.parent.mkdir(exist_ok=True)
        for name in names[::-1]:
            (copy.parent / name.name).write_bytes(name.read_bytes())
    except FileNotFoundError:
        return None
    try:
        return sitk.GetArrayFromImage(sitk.ReadImage(str(copy)))
    except RuntimeError:
        if target.suffix == ".mhd":
            return None
        raise


@pytest.mark.parametrize("suffix", [".nii.gz", ".mhd"])
def test_concurrent_writers_of_one_file_never_mix(tmp_path, suffix):
    script = tmp_path / "writer.py"
    script.write_text(WRITER, encoding="utf-8")
    target = tmp_path / "out" / f"label{suffix}"
    procs = [
        subprocess.Popen(_python(str(script), str(v), str(target), "60"), env=_env())
        for v in (1, 2)
    ]
    seen = set()
    while any(p.poll() is None for p in procs):
        arr = _snapshot(target, tmp_path / "snapshot" / target.name)
        if arr is not None:  # a reader at any moment sees a whole file of one writer
            assert arr.shape[0] in (9, 10) and len(np.unique(arr)) == 1
            seen.add(int(arr.flat[0]))
        time.sleep(0.005)
    assert all(p.returncode == 0 for p in procs)
    assert seen  # the reader did look while the writers ran
    final = sitk.GetArrayFromImage(sitk.ReadImage(str(target)))
    assert final.shape == (8 + int(final.flat[0]),) * 3 and len(np.unique(final)) == 1
    leftovers = sorted(p.name for p in target.parent.iterdir() if p.name.startswith(".tmp-"))
    assert leftovers == []


# ----------------------------------------------------------------------------- interruption

EVALUATE = textwrap.dedent(
    """
    import signal
    import sys
    import time

    import numpy as np
    import SimpleITK as sitk

    from medseg.evaluation.evaluate import run_evaluation
    from medseg.evaluation.methods import MethodSpec


    class _Result:
        def __init__(self, label, landmarks):
            self.label, self.landmarks, self.mrf = label, landmarks, None


    class SlowThreshold:
        # threshold at the training mid-intensity; landmarks: the training mean; each
        # segmentation takes `delay` seconds, so that a run can be interrupted midway
        def __init__(self, *, delay=0.0, log=None, random_state=None):
            self.delay, self.log, self.random_state = delay, log, random_state

        def fit(self, cohort):
            with open(self.log, "a", encoding="utf-8") as fh:
                fh.write(",".join(sorted(c.case_id for c in cohort)) + "\\n")
            rng = np.random.default_rng(self.random_state)
            lms = np.stack([c.load_landmarks() for c in cohort])
            self.landmarks_ = lms.mean(0) + 0.5 * rng.standard_normal(lms.shape[1:])
            arrays = [sitk.GetArrayFromImage(c.load_image()) for c in cohort]
            self.threshold_ = float(np.mean([(a.min() + a.max()) / 2 for a in arrays]))
            return self

        def segment(self, image, *, offset=0.0):
            time.sleep(self.delay)
            label = sitk.Cast(image > self.threshold_, sitk.sitkUInt8)
            return _Result(label, self.landmarks_ + offset)


    # a user's Ctrl-C raises KeyboardInterrupt; a shell starting the tests in the background
    # would have the child inherit SIGINT ignored, so the child says what it expects
    signal.signal(signal.SIGINT, signal.default_int_handler)
    dataset, output, log = sys.argv[1:4]
    spec = MethodSpec(
        SlowThreshold, {"delay": 0.15, "log": log}, {"thresh": {}, "shifted": {"offset": 1.0}}
    )
    run_evaluation(
        dataset, output, methods=[spec], perturbation=("pad_zeros",), seed=5, report=False
    )
    """
)


def _ball_cohort(folder: Path, n_subjects: int = 6) -> Path:
    from medseg.datasets import Case, Cohort, write_cohort
    from medseg.io import voxel_to_physical

    rng = np.random.default_rng(0)
    cases = []
    zyx = np.indices((16, 16, 16), dtype=float)
    for s in range(n_subjects):
        radius, centre = rng.uniform(3.5, 5.0), 7.5 + rng.uniform(-1.5, 1.5, 3)
        inside = ((zyx - centre[:, None, None, None]) ** 2).sum(0) <= radius**2
        image = sitk.GetImageFromArray((20.0 + 80.0 * inside).astype(np.float32))
        label = sitk.GetImageFromArray(inside.astype(np.uint8))
        label.CopyInformation(image)
        landmarks = voxel_to_physical(image, centre + np.vstack([np.eye(3), -np.eye(3)]) * radius)
        cases.append(Case(f"ball_{s:02d}", f"subj{s}", image, label, landmarks))
    cohort = Cohort(cases=cases, labels={"background": 0, "ball": 1}, name="balls")
    return write_cohort(cohort, folder)


@pytest.fixture(scope="module")
def evaluation_setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("resume")
    dataset = _ball_cohort(root / "balls")
    script = root / "evaluate.py"
    script.write_text(EVALUATE, encoding="utf-8")
    reference = root / "reference"
    done = subprocess.run(
        _python(str(script), str(dataset), str(reference), str(root / "reference.log")),
        env=_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    return root, dataset, script, read_results(reference / "cases.csv")


def _same(a: dict, b: dict, columns) -> bool:
    """Equal in every column (NaN equal to NaN)."""
    return all(
        a[c] == b[c] or (isinstance(a[c], float) and np.isnan(a[c]) and np.isnan(b[c]))
        for c in columns
    )


def _key(row: dict) -> tuple:
    return (row["method"], row["fold"], row["case"], row["perturbation"])


ROWS_PER_FOLD = 4  # one test case x 2 variants x (acquired, pad_zeros)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_interrupted_evaluation_resumes_without_recomputing(evaluation_setup, sig):
    root, dataset, script, reference = evaluation_setup
    assert len(reference) == 6 * ROWS_PER_FOLD
    # two rows per (variant, case), both at 0 degrees and scale 1: the key is the name
    assert {(r["perturbation"], r["perturbation_deg"], r["scale"]) for r in reference} == {
        ("acquired", 0.0, 1.0),
        ("pad_zeros", 0.0, 1.0),
    }
    out, log = root / f"run-{sig.name}", root / f"{sig.name}.log"
    argv = _python(str(script), str(dataset), str(out), str(log))
    proc = subprocess.Popen(argv, env=_env(), stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while len(read_results(out / "cases.csv")) < 6:  # at least one whole fold and a half
        assert proc.poll() is None and time.monotonic() < deadline, "finished before the kill"
        time.sleep(0.02)
    proc.send_signal(sig)
    assert proc.wait(timeout=60) != 0
    before = {_key(r): r for r in read_results(out / "cases.csv")}
    assert 6 <= len(before) < 6 * ROWS_PER_FOLD
    log.unlink()

    resumed = subprocess.run(argv, env=_env(), capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    rows = {_key(r): r for r in read_results(out / "cases.csv")}
    assert sorted(rows) == sorted(_key(r) for r in reference)  # each row once, none missing
    # finished rows were kept as they were (a recomputation would have a new timing) ...
    for key, row in before.items():
        assert _same(row, rows[key], COLUMNS)
    # ... and only the folds with missing rows were fitted again
    per_fold = [f for (_, f, _, _) in before]
    folds_done = {f for f in per_fold if per_fold.count(f) == ROWS_PER_FOLD}
    refits = log.read_text(encoding="utf-8").splitlines()
    assert len(refits) == 6 - len(folds_done)
    # the table equals an uninterrupted run's, timings aside
    by_ref = {_key(r): r for r in reference}
    values = [c for c in COLUMNS if c not in ("seconds", "fit_seconds")]
    for key, row in rows.items():
        assert _same(row, by_ref[key], values), key
