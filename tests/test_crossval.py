"""Cross-validation engine: folds by subject, bad input, CSV rows, resume, parallel runs,
and the named perturbation conditions shared with the pose-study benchmark.

These tests are about the engine, so they use a tiny fake method (intensity threshold +
mean training landmarks with a seeded jitter) on a tiny generated cohort of balls.
"""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from sklearn.utils import check_random_state

from medseg.datasets import Case, Cohort
from medseg.errors import CohortError, InputFileError, LabelError, MedsegError, ParameterError
from medseg.evaluation.folds import check_cohort, fold_seed, make_folds
from medseg.evaluation.methods import MethodSpec
from medseg.evaluation.perturbation import (
    CONDITIONS,
    PAD_MM,
    check_conditions,
    image_centre,
    parse_condition,
    perturb_case,
    perturb_condition,
    pose_change,
    random_similarity,
)
from medseg.evaluation.results import COLUMNS, read_results, result_key
from medseg.evaluation.runner import run_folds
from medseg.io import voxel_to_physical

SIZE = 20


def _ball_case(i: int, subject: str, rng: np.random.RandomState) -> Case:
    radius = rng.uniform(4.0, 6.0)
    centre_zyx = np.full(3, (SIZE - 1) / 2.0) + rng.uniform(-1.5, 1.5, 3)
    zyx = np.indices((SIZE,) * 3, dtype=float)
    inside = ((zyx - centre_zyx[:, None, None, None]) ** 2).sum(0) <= radius**2
    image = sitk.GetImageFromArray((20.0 + 80.0 * inside).astype(np.float32))
    image.SetSpacing((1.0, 1.0, 1.5))
    label = sitk.GetImageFromArray(inside.astype(np.uint8))
    label.CopyInformation(image)
    offsets = np.vstack([np.eye(3), -np.eye(3)]) * radius
    landmarks = voxel_to_physical(image, centre_zyx + offsets)
    return Case(f"ball_{i:02d}", subject, image, label, landmarks)


def tiny_cohort(n_subjects: int = 4, per_subject: int = 2, seed: int = 0) -> Cohort:
    rng = check_random_state(seed)
    cases = [
        _ball_case(s * per_subject + j, f"subj{s}", rng)
        for s in range(n_subjects)
        for j in range(per_subject)
    ]
    return Cohort(cases=cases, labels={"background": 0, "ball": 1}, name="balls")


class _Result:
    def __init__(self, label, landmarks):
        self.label, self.landmarks, self.mrf = label, landmarks, None


class ThresholdMethod:
    """Fake method for engine tests: threshold at the training mid-intensity."""

    def __init__(self, *, jitter: float = 0.5, log: str | None = None, random_state=None):
        self.jitter = jitter
        self.log = log
        self.random_state = random_state

    def fit(self, cohort):
        if self.log:
            with open(self.log, "a") as fh:
                fh.write(",".join(sorted(c.case_id for c in cohort)) + "\n")
        rng = check_random_state(self.random_state)
        lms = np.stack([c.load_landmarks() for c in cohort])
        self.landmarks_ = lms.mean(0) + self.jitter * rng.standard_normal(lms.shape[1:])
        arrays = [sitk.GetArrayFromImage(c.load_image()) for c in cohort]
        self.threshold_ = float(np.mean([(a.min() + a.max()) / 2.0 for a in arrays]))
        return self

    def segment(self, image, *, offset: float = 0.0):
        label = sitk.Cast(image > self.threshold_, sitk.sitkUInt8)
        return _Result(label, self.landmarks_ + offset)


class FailsOnOneCase(ThresholdMethod):
    """Fake method that raises a MedsegError on one case (a real failure mode, e.g.
    detected landmarks that coincide), to test that the run goes on."""

    def segment(self, image, *, offset: float = 0.0):
        if sitk.GetArrayViewFromImage(image).sum() == _FAILING_SUM[0]:
            raise MedsegError("landmarks 3 and 4 coincide")
        return super().segment(image, offset=offset)


_FAILING_SUM = [None]


def test_a_case_the_method_fails_on_is_recorded_and_the_run_goes_on(tmp_path, capsys):
    cohort = tiny_cohort(n_subjects=6, per_subject=1)
    failing = cohort[1]
    _FAILING_SUM[0] = sitk.GetArrayViewFromImage(failing.load_image()).sum()
    spec = (MethodSpec(FailsOnOneCase, {}, {"thresh": {}}),)
    out = run_folds(cohort, spec, tmp_path / "run", folds=6)
    rows = read_results(out)
    assert len(rows) == len(cohort)
    bad = [r for r in rows if r["case"] == failing.case_id]
    good = [r for r in rows if r["case"] != failing.case_id]
    assert len(bad) == 1 and bad[0]["dice"] == 0.0 and np.isnan(bad[0]["landmark_error_mm"])
    assert np.isinf(bad[0]["hd95"])
    assert all(r["dice"] > 0.5 and np.isfinite(r["landmark_error_mm"]) for r in good)
    assert f"thresh failed on {failing.case_id}" in capsys.readouterr().err


def _specs(log=None):
    return (
        MethodSpec(
            ThresholdMethod,
            {"log": log},
            {"thresh": {}, "shifted": {"offset": 1.0}},
        ),
    )


def _by_key(rows):
    return {(r["method"], r["fold"], r["case"], r["perturbation"]): r for r in rows}


# ----------------------------------------------------------------------------- folds


@pytest.mark.parametrize("folds", ["loo", 2, 3])
def test_folds_never_split_a_subject(folds):
    cohort = tiny_cohort(n_subjects=4, per_subject=2)
    splits = make_folds(cohort, folds)
    subjects = cohort.subjects
    tested = np.concatenate([te for _, te in splits])
    assert sorted(tested.tolist()) == list(range(len(cohort)))
    for tr, te in splits:
        assert not set(subjects[tr]) & set(subjects[te])
    assert len(splits) == (4 if folds == "loo" else folds)


def test_fold_seed_depends_on_seed_and_fold_only():
    assert fold_seed(0, 3) == fold_seed(0, 3)
    assert len({fold_seed(0, f) for f in range(10)} | {fold_seed(1, 0)}) == 11


# ----------------------------------------------------------------------------- bad input


def test_bad_input_is_refused_before_any_work(tmp_path):
    log = tmp_path / "fits.log"
    with pytest.raises(CohortError, match="empty"):
        run_folds(Cohort(cases=[]), _specs(str(log)), tmp_path / "a")
    one = tiny_cohort(n_subjects=1, per_subject=6)
    with pytest.raises(CohortError, match="single subject"):
        run_folds(one, _specs(str(log)), tmp_path / "b")
    cohort = tiny_cohort(n_subjects=6, per_subject=1)
    with pytest.raises(LabelError, match=r"\[2\] occur in no case"):
        run_folds(cohort, _specs(str(log)), tmp_path / "c", labels=(1, 2))
    with pytest.raises(CohortError, match="only 6 subjects"):
        run_folds(cohort, _specs(str(log)), tmp_path / "d", folds=7)
    small = tiny_cohort(n_subjects=3, per_subject=2)
    with pytest.raises(CohortError, match="would train on 4"):
        check_cohort(small, labels=(1,), folds=3)
    with pytest.raises(MedsegError, match="folds"):
        make_folds(cohort, "kfold")
    assert not log.exists()
    assert not any((tmp_path / d / "cases.csv").exists() for d in "abcd")


# ----------------------------------------------------------------------------- runs


STUDY = ("rot30", "scale1.25", "pad_zeros", "random")


def test_rows_scores_and_perturbation(tmp_path):
    cohort = tiny_cohort(n_subjects=8, per_subject=1)
    path = run_folds(cohort, _specs(), tmp_path, folds=4, seed=1, perturbation=STUDY)
    with path.open() as fh:
        assert tuple(next(csv.reader(fh))) == COLUMNS
    rows = read_results(path)
    assert len(rows) == 2 * 8 * 5  # methods x cases x (acquired + 4 conditions)
    by = _by_key(rows)
    for method in ("thresh", "shifted"):
        for case in cohort:
            conditions = {c for (m, _, k, c) in by if m == method and k == case.case_id}
            assert conditions == {"acquired", *STUDY}
    for r in rows:
        condition = r["perturbation"]
        if condition in ("acquired", "pad_zeros"):
            # A clean two-level image thresholded in the middle is the label exactly, also
            # in a field of view padded with zeros (the threshold is above 0).
            assert r["dice"] == 1.0 and r["hd95"] == 0.0 and r["assd"] == 0.0
            assert r["perturbation_deg"] == 0.0 and r["scale"] == 1.0
        else:
            if condition == "rot30":
                assert r["perturbation_deg"] == pytest.approx(30.0) and r["scale"] == 1.0
            elif condition == "scale1.25":
                assert r["perturbation_deg"] == 0.0 and r["scale"] == 1.25
            else:
                assert 0.0 <= r["perturbation_deg"] <= 45.0 and 0.8 <= r["scale"] <= 1.25
            # The reference follows the image: the label resampled label-linearly is its
            # indicator interpolated linearly above one half, which is what thresholding the
            # linearly resampled two-level image keeps (by nearest neighbour the rows were
            # 0.93-0.97 under rot30 and scale1.25; label-linearly 0.988-1.0).
            assert r["dice"] > 0.98
        assert np.isnan(r["gap"]) and r["seconds"] >= 0
    for condition in ("rot30", "scale1.25"):
        assert np.mean([r["dice"] for r in rows if r["perturbation"] == condition]) > 0.99
    # One perturbed copy per (case, condition), shared by the methods; seeded per case.
    for case in cohort:
        fold = next(f for (_, f, k, _) in by if k == case.case_id)
        a, b = by[("thresh", fold, case.case_id, "random")], by[("shifted", fold, case.case_id,
                                                                   "random")]  # fmt: skip
        assert (a["perturbation_deg"], a["scale"]) == (b["perturbation_deg"], b["scale"])
    randoms = {(r["perturbation_deg"], r["scale"]) for r in rows if r["perturbation"] == "random"}
    assert len(randoms) == 8
    # The shifted variant moves every landmark by (1, 1, 1) mm from the same fit.
    for (method, fold, case, condition), r in by.items():
        if method == "thresh" and condition == "acquired":
            case_ = next(c for c in cohort if c.case_id == case)
            assert r["landmark_error_mm"] > 0
            assert (
                r["landmark_error_mm"]
                != by[("shifted", fold, case, condition)]["landmark_error_mm"]
            )
            assert r["subject"] == case_.subject


def test_a_perturbed_copy_depends_on_the_seed_case_and_condition_only(tmp_path):
    cohort = tiny_cohort(n_subjects=8, per_subject=1)
    full = _by_key(read_results(run_folds(cohort, _specs(), tmp_path / "a", folds=4, seed=1,
                                          perturbation=STUDY)))  # fmt: skip
    # another list of conditions, in another order: the same random copies
    alone = _by_key(read_results(run_folds(cohort, _specs(), tmp_path / "b", folds=4, seed=1,
                                           perturbation=("random", "rot30.0"))))  # fmt: skip
    assert len(alone) == 2 * 8 * 3  # "rot30.0" is "rot30"
    for key, row in alone.items():
        for col in ("perturbation_deg", "scale", "dice", "hd95"):
            assert row[col] == full[key][col]
    other = _by_key(read_results(run_folds(cohort, _specs(), tmp_path / "c", folds=4, seed=2,
                                           perturbation=("random",))))  # fmt: skip
    changed = [k for k in other if k[3] == "random" and other[k]["scale"] != full[k]["scale"]]
    assert len(changed) == 2 * 8


def test_unknown_conditions_and_old_results_files_are_refused(tmp_path, capfd):
    cohort = tiny_cohort(n_subjects=6, per_subject=1)
    log = tmp_path / "fits.log"
    for bad in (("rot200",), ("random", "scale2"), (30.0,), ("flip",)):
        with pytest.raises(ParameterError, match="unknown perturbation condition"):
            run_folds(cohort, _specs(str(log)), tmp_path / "a", perturbation=bad)
    assert not log.exists() and not (tmp_path / "a").exists()
    # medseg-evaluate: one line, before the dataset is even read
    from medseg.evaluation.cli import main as evaluate_main

    code = evaluate_main(["no-such-dataset", "-o", str(tmp_path / "b"), "--perturbation",
                          "random,rot200", "-q"])  # fmt: skip
    err = capfd.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "'rot200'" in err[0] and "rotN" in err[0]
    assert not (tmp_path / "b").exists()
    # a results file of the earlier format (no perturbation column): a clear error, and the
    # file is left as it was (not rewritten without its rows)
    old = tmp_path / "old"
    old.mkdir()
    header = [c for c in COLUMNS if c != "perturbation"]
    text = ",".join(header) + "\n" + ",".join(["thresh", "0", "ball_00", "subj0"] + ["0.0"]
                                               * (len(header) - 4)) + "\n"  # fmt: skip
    (old / "cases.csv").write_text(text)
    with pytest.raises(InputFileError, match="lacks the column.*perturbation"):
        read_results(old / "cases.csv")
    with pytest.raises(InputFileError, match="another version"):
        run_folds(cohort, _specs(str(log)), old, folds="loo", seed=3)
    assert (old / "cases.csv").read_text() == text and not log.exists()


def test_result_key_tells_conditions_of_the_same_angle_apart():
    keys = {result_key("m", 0, "a", c) for c in ("acquired", "pad_zeros", "scale0.8")}
    assert len(keys) == 3
    assert result_key("m", 0, "a", "rot90") == result_key("m", np.int64(0), "a", "rot90")


def test_resume_recomputes_only_missing_rows(tmp_path):
    cohort = tiny_cohort(n_subjects=6, per_subject=1)
    log = tmp_path / "fits.log"
    # two conditions that rotate by 0 degrees, as the unperturbed case does: rows are told
    # apart by the condition's name
    study = {"folds": "loo", "seed": 3, "perturbation": ("pad_zeros", "scale0.9")}
    full = run_folds(cohort, _specs(str(log)), tmp_path / "full", **study)
    reference = _by_key(read_results(full))
    assert len(reference) == 6 * 2 * 3  # cases x variants x conditions
    assert {r["perturbation_deg"] for r in reference.values()} == {0.0}
    assert len(log.read_text().splitlines()) == 6

    # An interrupted run: the first 15 rows (folds 0, 1 and half of fold 2) and a torn line.
    part = tmp_path / "part"
    part.mkdir()
    (part / "run.json").write_text((tmp_path / "full" / "run.json").read_text())
    lines = full.read_text().splitlines()
    (part / "cases.csv").write_text("\n".join(lines[:16]) + "\n" + lines[16][:15])
    log.unlink()
    run_folds(cohort, _specs(str(log)), part, **study)
    assert len(log.read_text().splitlines()) == 4  # folds 2..5 refitted, 0 and 1 skipped
    resumed = read_results(part / "cases.csv")
    assert len(resumed) == len(reference)
    assert sorted(_by_key(resumed)) == sorted(reference)
    for key, row in _by_key(resumed).items():
        for col in COLUMNS:
            if col not in ("seconds", "fit_seconds"):
                assert row[col] == reference[key][col] or (
                    np.isnan(row[col]) and np.isnan(reference[key][col])
                )
    # Nothing left to do: no fit at all.
    log.unlink()
    run_folds(cohort, _specs(str(log)), part, **study)
    assert not log.exists()
    # A condition added on resume: only its rows are computed, the others kept as they were.
    before = _by_key(read_results(part / "cases.csv"))
    run_folds(cohort, _specs(str(log)), part, **(study | {"perturbation": ("rot45", "pad_zeros")}))
    after = _by_key(read_results(part / "cases.csv"))
    assert len(after) == len(before) + 6 * 2
    assert all(after[k]["seconds"] == before[k]["seconds"] for k in before)
    assert {k[3] for k in set(after) - set(before)} == {"rot45"}
    with pytest.raises(MedsegError, match="seed"):
        run_folds(cohort, _specs(str(log)), part, folds="loo", seed=4)
    other_params = (MethodSpec(ThresholdMethod, {"jitter": 0.1}, {"thresh": {}}),)
    with pytest.raises(MedsegError, match="method 'thresh'"):
        run_folds(cohort, other_params, part, folds="loo", seed=3)
    # ... unless the method has no rows yet (an extension stopped before its first fold
    # ended): its recorded settings are then replaced, not a reason to refuse
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / "run.json").write_text((part / "run.json").read_text())
    run_folds(cohort, other_params, fresh, folds="loo", seed=3)
    assert json.loads((fresh / "run.json").read_text())["methods"]["thresh"]["params"] == (
        "[('jitter', 0.1)]"
    )
    with pytest.raises(MedsegError, match="method 'thresh'"):
        run_folds(cohort, _specs(str(log)), fresh, folds="loo", seed=3)  # now it has rows
    # a folder scored against references resampled otherwise (before 2026-12-04: nearest
    # neighbour, a run.json without the key) is not resumed
    config = json.loads((part / "run.json").read_text())
    assert config.pop("reference_labels") == "linear"
    (part / "run.json").write_text(json.dumps(config))
    with pytest.raises(MedsegError, match="reference_labels"):
        run_folds(cohort, _specs(str(log)), part, **study)


def _register_by_value():
    # Worker processes cannot import this test module: ship the fake method by value
    # (joblib's loky and dask both pickle with cloudpickle).
    import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])


def _values(path: Path) -> dict:
    return {
        k: tuple(
            None if isinstance(v, float) and np.isnan(v) else v
            for c, v in r.items()
            if c not in ("seconds", "fit_seconds")
        )
        for k, r in _by_key(read_results(path)).items()
    }


def test_parallel_runs_equal_the_serial_run(tmp_path):
    _register_by_value()
    cohort = tiny_cohort(n_subjects=4, per_subject=2)
    kwargs = {"folds": 4, "seed": 7, "perturbation": ("rot20", "random")}
    serial = run_folds(cohort, _specs(), tmp_path / "serial", **kwargs)
    local = run_folds(cohort, _specs(), tmp_path / "joblib", n_jobs=2, **kwargs)
    assert _values(local) == _values(serial)

    from dask.distributed import LocalCluster

    with LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        dask_csv = run_folds(
            cohort, _specs(), tmp_path / "dask", scheduler=cluster.scheduler_address, **kwargs
        )
    assert _values(dask_csv) == _values(serial)
    other = run_folds(cohort, _specs(), tmp_path / "other", **(kwargs | {"seed": 8}))
    assert _values(other) != _values(serial)


def test_unreachable_scheduler_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setattr("medseg.evaluation.runner.DASK_CONNECT_TIMEOUT", "1s")
    cohort = tiny_cohort(n_subjects=6, per_subject=1)
    with pytest.raises(MedsegError, match="Dask scheduler"):
        run_folds(cohort, _specs(), tmp_path, scheduler="tcp://127.0.0.1:9")


# ----------------------------------------------------------------------------- perturbation


@pytest.mark.parametrize("angle", [0.0, 20.0, 45.0])
def test_random_similarity_has_the_requested_size(angle):
    change = random_similarity(angle, random_state=0)
    cos = (np.trace(change.rotation) - 1.0) / 2.0
    assert np.rad2deg(np.arccos(np.clip(cos, -1, 1))) == pytest.approx(angle, abs=1e-6)
    assert abs(np.log(change.scale)) == pytest.approx(np.log(1.25) * angle / 45.0)
    np.testing.assert_allclose(change.rotation @ change.rotation.T, np.eye(3), atol=1e-12)


def test_perturbed_case_keeps_grid_and_moves_landmarks_with_the_label():
    case = tiny_cohort(n_subjects=1, per_subject=1, seed=5)[0]
    image, label = case.load_image(), case.load_label()
    change = random_similarity(40.0, random_state=2)
    moved_image, moved_label, moved_lm = perturb_case(image, label, case.landmarks, change)
    for a in (moved_image, moved_label):
        assert a.GetSize() == image.GetSize() and a.GetSpacing() == image.GetSpacing()
        assert a.GetOrigin() == image.GetOrigin() and a.GetDirection() == image.GetDirection()
    assert moved_label.GetPixelID() == sitk.sitkUInt8
    assert set(np.unique(sitk.GetArrayViewFromImage(moved_label))) <= {0, 1}
    # Volume scales with scale^3; the ball's landmarks stay on the moved ball's boundary.
    v0 = sitk.GetArrayViewFromImage(label).sum()
    v1 = sitk.GetArrayViewFromImage(moved_label).sum()
    assert v1 / v0 == pytest.approx(change.scale**3, rel=0.08)
    fg = voxel_to_physical(moved_label, np.argwhere(sitk.GetArrayViewFromImage(moved_label)))
    centre = fg.mean(0)
    np.testing.assert_allclose(moved_lm.mean(0), centre, atol=0.3)
    radius = np.linalg.norm(case.landmarks - case.landmarks.mean(0), axis=1)
    np.testing.assert_allclose(
        np.linalg.norm(moved_lm - centre, axis=1), change.scale * radius, atol=0.3
    )


@pytest.mark.parametrize("fill", ["zeros", "noise", "border"])
def test_padded_field_of_view_keeps_the_voxels_and_fills_the_rest(fill):
    case = tiny_cohort(n_subjects=1, per_subject=1, seed=5)[0]
    image, label = case.load_image(), case.load_label()
    still = pose_change(angle_deg=0.0)
    moved_image, moved_label, moved_lm = perturb_case(
        image, label, case.landmarks, still, pad_mm=6.0, fill=fill, random_state=0
    )
    pad = np.ceil(6.0 / np.asarray(image.GetSpacing())).astype(int)[::-1]  # (z, y, x)
    assert moved_image.GetSize() == tuple(int(s) + 2 * int(p) for s, p in
                                          zip(image.GetSize(), pad[::-1], strict=True))  # fmt: skip
    assert moved_image.GetDirection() == image.GetDirection()
    big = sitk.GetArrayFromImage(moved_image)
    inner = tuple(slice(p, -p) for p in pad)
    np.testing.assert_allclose(big[inner], sitk.GetArrayFromImage(image), atol=1e-4)
    np.testing.assert_array_equal(
        sitk.GetArrayFromImage(moved_label)[inner], sitk.GetArrayFromImage(label)
    )
    # the same physical points: voxel -> mm through each image's own geometry
    np.testing.assert_allclose(
        moved_image.TransformIndexToPhysicalPoint([int(p) for p in pad[::-1]]),
        image.GetOrigin(), atol=1e-9,
    )  # fmt: skip
    np.testing.assert_allclose(moved_lm, case.landmarks)
    outside = np.ones(big.shape, dtype=bool)
    outside[inner] = False
    a = sitk.GetArrayFromImage(image).astype(float)
    border = np.concatenate([f.ravel() for f in (a[0], a[-1], a[:, 0], a[:, -1], a[..., 0],
                                                 a[..., -1])])  # fmt: skip
    if fill == "zeros":
        assert np.all(big[outside] == 0)
    elif fill == "noise":  # the border's mean and spread
        assert big[outside].mean() == pytest.approx(border.mean(), abs=0.1 * border.std() + 1e-3)
        assert big[outside].std() == pytest.approx(border.std(), rel=0.1)
    else:
        np.testing.assert_allclose(big[outside], np.median(border), rtol=1e-6)


def test_pose_change_of_a_given_size():
    change = pose_change(angle_deg=120.0, scale=0.8, random_state=3)
    assert change.scale == 0.8 and change.angle_deg == 120.0
    angle = np.degrees(np.arccos((np.trace(change.rotation) - 1) / 2))
    assert angle == pytest.approx(120.0)
    with pytest.raises(ParameterError):
        pose_change(angle_deg=200.0)
    with pytest.raises(ParameterError):
        perturb_case(sitk.Image(4, 4, 4, sitk.sitkUInt8), sitk.Image(4, 4, 4, sitk.sitkUInt8),
                     None, change, fill="mirror")  # fmt: skip


def test_condition_names_are_parsed_generally_and_canonically():
    assert [parse_condition(c).name for c in CONDITIONS] == list(CONDITIONS)
    rot = parse_condition("rot22.50")
    assert (rot.name, rot.kind, rot.angle_deg, rot.scale) == ("rot22.5", "rotation", 22.5, 1.0)
    assert parse_condition("rot180").angle_deg == 180 and parse_condition("rot0").name == "rot0"
    scale = parse_condition("scale.8")
    assert (scale.name, scale.kind, scale.scale, scale.angle_deg) == ("scale0.8", "scale", 0.8, 0)
    assert parse_condition("scale1.999").scale == 1.999
    assert parse_condition("pad_noise").fill == "noise" and parse_condition("random").pad_mm == 15
    assert parse_condition("acquired").pad_mm == 0
    for bad in ("rot181", "rot-5", "rot", "rotnan", "scale0.5", "scale2", "scale1e0", "Random",
                "pad_border", "", 45, None):  # fmt: skip
        with pytest.raises(ParameterError, match="unknown perturbation condition"):
            parse_condition(bad)
    assert check_conditions(()) == ("acquired",)
    assert check_conditions(["random", "rot90.0", "acquired", "rot90"]) == (
        "acquired",
        "random",
        "rot90",
    )
    assert check_conditions("scale1.1") == ("acquired", "scale1.1")


def _centred_ball():
    case = tiny_cohort(n_subjects=1, per_subject=1, seed=5)[0]
    return case, case.load_image(), case.load_label()


def test_rotation_condition_turns_about_the_image_centre_on_the_padded_grid():
    case, image, label = _centred_ball()
    moved, moved_label, moved_lm, change, centre = perturb_condition(
        "rot90", image, label, case.landmarks, random_state=4
    )
    assert change.angle_deg == 90.0 and change.scale == 1.0
    np.testing.assert_allclose(centre, image_centre(image))
    np.testing.assert_allclose(centre, np.asarray(image.GetOrigin()) + np.array([9.5, 9.5, 14.25]))
    pad = np.ceil(PAD_MM / np.asarray(image.GetSpacing())).astype(int)
    assert moved.GetSize() == tuple(int(v) for v in np.asarray(image.GetSize()) + 2 * pad)
    assert moved_label.GetSize() == moved.GetSize() and moved.GetSpacing() == image.GetSpacing()
    np.testing.assert_allclose(image_centre(moved), centre, atol=1e-9)  # same centre
    arr = sitk.GetArrayFromImage(moved)
    assert arr[0, 0, 0] == 0 and arr.max() == pytest.approx(100.0)  # zeros outside
    np.testing.assert_allclose(moved_lm, change.apply(case.landmarks, centre))
    # the ball's label moved with its landmarks (their centroid is the ball's centre)
    fg = voxel_to_physical(moved_label, np.argwhere(sitk.GetArrayViewFromImage(moved_label)))
    np.testing.assert_allclose(fg.mean(0), moved_lm.mean(0), atol=0.4)
    v0 = sitk.GetArrayViewFromImage(label).sum()
    assert sitk.GetArrayViewFromImage(moved_label).sum() == pytest.approx(v0, rel=0.08)
    # the same seed, the same copy; another seed, another axis
    again = perturb_condition("rot90", image, label, case.landmarks, random_state=4)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(again[0]), arr)
    other = perturb_condition("rot90", image, label, case.landmarks, random_state=5)
    assert not np.allclose(other[3].rotation, change.rotation)


def test_scale_pad_random_and_acquired_conditions():
    case, image, label = _centred_ball()
    v0 = sitk.GetArrayViewFromImage(label).sum()
    _, scaled, lm, change, centre = perturb_condition("scale0.8", image, label, case.landmarks)
    assert change.scale == 0.8 and change.angle_deg == 0.0
    assert sitk.GetArrayViewFromImage(scaled).sum() / v0 == pytest.approx(0.8**3, rel=0.1)
    np.testing.assert_allclose(lm - centre, 0.8 * (case.landmarks - centre))
    same = perturb_condition("acquired", image, label, case.landmarks, random_state=0)
    assert same[0] is image and same[1] is label and same[3].scale == 1.0
    np.testing.assert_array_equal(same[2], case.landmarks)
    # noise like the border's (the ball's background, with noise added here)
    voxels = sitk.GetArrayFromImage(image) + np.random.default_rng(0).normal(0, 2, (SIZE,) * 3)
    textured = sitk.GetImageFromArray(voxels.astype(np.float32))
    textured.CopyInformation(image)
    noisy = [perturb_condition("pad_noise", textured, label, random_state=s)[0] for s in (0, 0, 1)]
    a, b, c = (sitk.GetArrayFromImage(n) for n in noisy)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c) and a[0].std() == pytest.approx(2.0, rel=0.2)
    draws = [perturb_condition("random", image, label, random_state=s)[3] for s in range(40)]
    angles = np.array([d.angle_deg for d in draws])
    scales = np.array([d.scale for d in draws])
    assert angles.min() >= 0 and angles.max() <= 45 and angles.std() > 5
    assert scales.min() >= 0.8 and scales.max() <= 1.25
    assert (scales < 1).any() and (scales > 1).any()


# ----------------------------------------------------------------------------- references


def test_transferred_reference_landmarks_match_the_phantom_truth():
    from medseg.correspondence import label_surface, transfer_landmarks
    from medseg.datasets import make_phantom_cohort

    a, b = make_phantom_cohort(2, size=48, random_state=0)
    moved = transfer_landmarks(
        label_surface(a.load_label()),
        a.landmarks,
        b.load_label(),
        n_registration_points=200,
        random_state=0,
    )
    error = np.linalg.norm(moved - b.landmarks, axis=1)
    # Exact ground-truth correspondence exists on the phantom; 1 mm voxels, ~6 mm between
    # neighbouring landmarks: a mirrored or rigid-only transfer is several mm off.
    assert error.mean() < 2.0


class TwoLabelMethod(ThresholdMethod):
    """Fake method of a two-label structure: the thresholded ball, label 2 beyond the
    middle slice; its ``shape_label`` the whole ball as label 1 (no second label)."""

    def segment(self, image, *, offset: float = 0.0):
        result = super().segment(image, offset=offset)
        inside = sitk.GetArrayFromImage(result.label)
        upper = np.arange(inside.shape[0])[:, None, None] > SIZE // 2
        label = sitk.GetImageFromArray((inside * (1 + upper)).astype(np.uint8))
        label.CopyInformation(image)
        result.shape_label, result.label = result.label, label
        result.quality = {"score": 2.5, "flagged": False}
        return result


def test_labels_of_a_structure_of_two_are_scored_each_and_a_derived_map_costs_no_fit(tmp_path):
    from medseg.evaluation.report import summarise

    cases = []
    for case in tiny_cohort(n_subjects=10, per_subject=1):
        label = sitk.GetArrayFromImage(case.load_label())
        centre = np.argwhere(label).mean(axis=0)[0]
        upper = np.arange(SIZE)[:, None, None] > centre
        two = sitk.GetImageFromArray((label * (1 + upper)).astype(np.uint8))
        two.CopyInformation(case.load_label())
        cases.append(Case(case.case_id, case.subject, case.load_image(), two, case.landmarks))
    cohort = Cohort(cases=cases, labels={"background": 0, "a": 1, "b": 2}, name="halves")
    log = tmp_path / "fits.log"
    spec = MethodSpec(
        TwoLabelMethod, {"log": str(log)}, {"two": {}}, {"plain": ("two", "shape_label")}
    )
    rows = read_results(run_folds(cohort, (spec,), tmp_path / "run", folds=2, labels=(1, 2)))
    assert len(log.read_text().splitlines()) == 2  # one fit per fold for both methods
    by = _by_key(rows)
    for case in cohort:
        fold = next(f for (_, f, k, _) in by if k == case.case_id)
        two, plain = (by[(m, fold, case.case_id, "acquired")] for m in ("two", "plain"))
        # the same union (the thresholded ball), scored alike; per label, only "two" has 2
        assert two["dice"] == plain["dice"] == 1.0 and two["hd95"] == plain["hd95"] == 0.0
        parts = dict(p.split(":") for p in two["dice_by_label"].split(";"))
        assert set(parts) == {"1", "2"} and all(float(d) > 0.8 for d in parts.values())
        assert dict(p.split(":") for p in plain["dice_by_label"].split(";"))["2"] == "0.000000"
        # the segmenter's quality score is kept with both of its label maps
        assert two["quality"] == plain["quality"] == 2.5
    by_label = summarise(rows)["by_label"]
    assert by_label["two"][2] > 0.8 and by_label["plain"][2] == 0.0
    # a file written before the dice_by_label and quality columns still reads
    path = tmp_path / "run" / "cases.csv"
    header = [c for c in COLUMNS if c not in ("dice_by_label", "quality")]
    with path.open(newline="") as fh:
        old = [{c: r[c] for c in header} for r in csv.DictReader(fh)]
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=header)
        writer.writeheader()
        writer.writerows(old)
    again = read_results(path)
    assert len(again) == len(rows) and all(math.isnan(r["quality"]) for r in again)


class LoggingMethod(ThresholdMethod):
    """Fake method that writes a line to its log at each segmentation."""

    def segment(self, image, *, offset: float = 0.0):
        with open(self.log, "a") as fh:
            fh.write("segment\n")
        return super().segment(image, offset=offset)


def _ball_from_landmarks(estimator, image, reference_landmarks):
    """Oracle of the engine test: the ball through the reference landmarks (their centre and
    mean radius, in voxels); None at its first call of each fold (no row is then written)."""
    estimator.oracle_calls_ = getattr(estimator, "oracle_calls_", 0) + 1
    if estimator.oracle_calls_ == 1:
        return None
    xyz = np.asarray(
        [image.TransformPhysicalPointToContinuousIndex(p) for p in reference_landmarks]
    )  # the balls are round in voxels
    centre = xyz.mean(axis=0)[::-1]
    radius = np.linalg.norm(xyz - xyz.mean(axis=0), axis=1).mean()
    zyx = np.indices(image.GetSize()[::-1], dtype=float)
    inside = ((zyx - centre[:, None, None, None]) ** 2).sum(0) <= radius**2
    label = sitk.GetImageFromArray(inside.astype(np.uint8))
    label.CopyInformation(image)
    return _Result(label, None)


def test_an_oracle_added_on_resume_sees_the_reference_and_segments_nothing_again(tmp_path):
    cohort = tiny_cohort(n_subjects=10, per_subject=1)
    log = tmp_path / "calls.log"
    plain = MethodSpec(LoggingMethod, {"log": str(log)}, {"plain": {}})
    rows = read_results(run_folds(cohort, (plain,), tmp_path / "run", folds=2))
    assert {r["method"] for r in rows} == {"plain"} and len(rows) == len(cohort)
    assert log.read_text().splitlines().count("segment") == len(cohort)
    with_oracle = MethodSpec(
        LoggingMethod,
        {"log": str(log)},
        {"plain": {}},
        oracles={"oracle": ("plain", _ball_from_landmarks)},
    )
    rows = read_results(run_folds(cohort, (with_oracle,), tmp_path / "run", folds=2))
    # the resume fitted each fold again for the oracle but segmented nothing; each fold's
    # first oracle call gave None and wrote no row
    assert log.read_text().splitlines().count("segment") == len(cohort)
    oracle = [r for r in rows if r["method"] == "oracle"]
    assert len(oracle) == len(cohort) - 2
    for row in oracle:  # the ball through the true landmarks is the true ball
        assert row["dice"] > 0.95 and math.isnan(row["landmark_error_mm"])


class SavedThreshold(ThresholdMethod):
    """The fake method with the persistence the fold's model cache looks for."""

    def save(self, folder):
        folder = Path(folder)
        folder.mkdir(parents=True)
        record = {"landmarks": self.landmarks_.tolist(), "threshold": self.threshold_}
        (folder / "model.json").write_text(json.dumps(record))
        return folder

    @classmethod
    def load(cls, folder):
        record = json.loads((Path(folder) / "model.json").read_text())
        model = cls()
        model.landmarks_ = np.asarray(record["landmarks"])
        model.threshold_ = float(record["threshold"])
        return model


def test_kept_models_are_reused_only_when_they_were_fitted_alike(tmp_path, monkeypatch):
    from medseg.evaluation import fold as fold_module

    cohort = tiny_cohort(n_subjects=6, per_subject=1)
    log = tmp_path / "fits.log"

    def specs(jitter=0.5):
        return (MethodSpec(SavedThreshold, {"log": str(log), "jitter": jitter}, {"t": {}}),)

    def fits():
        n = len(log.read_text().splitlines()) if log.exists() else 0
        log.unlink(missing_ok=True)
        return n

    study = {"folds": "loo", "seed": 3, "keep_models": True}
    run = tmp_path / "run"
    run_folds(cohort, specs(), run, perturbation=(), **study)
    assert fits() == 6
    kept = sorted(p.name for p in (run / "models").iterdir())
    assert kept == [f"fold{k}_t" for k in range(6)]
    recorded = json.loads((run / "models" / "fold2_t" / "fit.json").read_text())

    # extended by a condition: every fold loads its model, and scores as a fresh fit does
    run_folds(cohort, specs(), run, perturbation=("rot45",), **study)
    assert fits() == 0
    fresh = run_folds(cohort, specs(), tmp_path / "fresh", folds="loo", seed=3,
                      perturbation=("rot45",))  # fmt: skip
    assert fits() == 6
    extended, reference = _by_key(read_results(run / "cases.csv")), _by_key(read_results(fresh))
    assert sorted(extended) == sorted(reference)
    for key, row in extended.items():
        assert row["dice"] == reference[key]["dice"]
        if key[3] == "rot45" and key[1] == 2:
            assert row["fit_seconds"] == recorded["fit_seconds"]

    # a model fitted by other code, or whose record is torn, is fitted again and replaced
    (run / "models" / "fold4_t" / "fit.json").write_text("{")
    run_folds(cohort, specs(), run, perturbation=("rot45", "pad_zeros"), **study)
    assert fits() == 1
    monkeypatch.setattr(fold_module, "_code_digest", lambda: "other source")
    run_folds(cohort, specs(), run, perturbation=("rot45", "pad_zeros", "scale0.9"), **study)
    assert fits() == 6
    assert json.loads((run / "models" / "fold0_t" / "fit.json").read_text())["code"] == (
        "other source"
    )
