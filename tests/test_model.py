"""The segmenter end to end on a small phantom: geometry, persistence, errors, CLIs."""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk

import medseg
from medseg.datasets import make_phantom_cohort, write_cohort
from medseg.errors import CohortError, ModelFileError, NotFittedError
from medseg.inference.cli import main as segment_main
from medseg.io import (
    image_geometry,
    load_arrays,
    physical_to_voxel,
    read_image,
    read_landmarks,
    save_arrays,
)
from medseg.segmenter import ShapePriorSegmenter, load_model
from medseg.training.cli import main as train_main

SMALL = dict(n_landmarks=12, size=48)


@pytest.fixture(scope="module")
def cohort():
    return make_phantom_cohort(8, random_state=1, **SMALL)


@pytest.fixture(scope="module")
def fitted(cohort):
    model = ShapePriorSegmenter(
        n_estimators=6, n_candidates=8, max_iter=100, random_state=0, n_jobs=2
    )
    return model.fit(cohort[:6])


@pytest.fixture(scope="module")
def saved(fitted, tmp_path_factory) -> Path:
    return fitted.save(tmp_path_factory.mktemp("model") / "model")


def test_segmentation_is_in_the_input_geometry_with_a_certified_bound(fitted, cohort):
    image = cohort[7].load_image()
    seg = fitted.segment(image)
    assert image_geometry(seg.label) == image_geometry(image)
    assert seg.landmarks.shape == (12, 3)
    assert seg.candidates.positions.shape == (12, 8, 3)
    assert seg.mrf.lower_bound <= seg.mrf.energy + 1e-6
    assert seg.confidence.shape == (12,) and np.all(seg.confidence >= 0)
    assert sitk.GetArrayViewFromImage(seg.label).any()


def test_the_regional_stage_is_on_by_default_and_can_be_turned_off(fitted, cohort):
    image = cohort[7].load_image()
    seg = fitted.segment(image)
    assert fitted.boundary_ is not None and "boundary" in seg.timings
    assert image_geometry(seg.shape_label) == image_geometry(image)
    refined, shape = (sitk.GetArrayFromImage(x) for x in (seg.label, seg.shape_label))
    assert set(np.unique(refined)) == {0, 1} and not np.array_equal(refined, shape)
    off = copy.copy(fitted)
    off.boundary = False
    plain = off.segment(image)
    assert "boundary" not in plain.timings
    np.testing.assert_array_equal(sitk.GetArrayFromImage(plain.label), shape)


def test_oblique_anisotropic_input_keeps_its_geometry(fitted):
    other = make_phantom_cohort(1, random_state=5, anisotropic=True, oblique=True, **SMALL)
    image = other[0].load_image()
    assert image.GetSpacing()[2] != image.GetSpacing()[0]
    seg = fitted.segment(image)
    assert image_geometry(seg.label) == image_geometry(image)


def test_inference_after_detection_assumes_no_pose(fitted, cohort):
    """The same candidates moved with a rigidly rotated image: the triplet prior and the
    solver give the identical choice. Not asserted: the handedness term and the active-shape
    refinement, which read the resampled image (its gradients and profiles move a little
    with the interpolation), nor detection; they are measured by the perturbation study."""
    from scipy.spatial.transform import Rotation

    from medseg.evaluation.perturbation import PoseChange, perturb_case

    image, label = cohort[7].load_image(), cohort[7].load_label()
    rotation = Rotation.from_rotvec(np.deg2rad(35.0) * np.array([0.6, -0.3, 0.74])).as_matrix()
    change = PoseChange(rotation=rotation, scale=1.0, angle_deg=35.0)
    centre = np.array([1.5, -2.0, 0.5])
    moved_image, _, _ = perturb_case(image, label, None, change, centre=centre)
    cands = fitted.detector_.candidates(image, n_candidates=fitted.n_candidates)
    moved = cands.mapped(lambda p: change.apply(p, centre), moved_image)
    plain = copy.copy(fitted)
    plain.orientation_weight = 0.0  # only the exactly invariant tables
    plain.refine_levels = 0  # the MRF's choice: hypotheses are kept by the image's profiles
    a = plain.segment(image, candidates=cands)
    b = plain.segment(moved_image, candidates=moved)
    np.testing.assert_array_equal(b.mrf.x, a.mrf.x)
    np.testing.assert_allclose(b.chosen, change.apply(a.chosen, centre), atol=1e-9)


def test_a_pass_in_the_shape_frame_answers_in_the_input_space(fitted, cohort):
    other = make_phantom_cohort(1, random_state=5, anisotropic=True, oblique=True, **SMALL)
    image = other[0].load_image()
    second = copy.copy(fitted).set_params(frame_passes=1)
    seg = second.segment(image)
    assert seg.frame_pose is not None and fitted.segment(image).frame_pose is None
    assert image_geometry(seg.label) == image_geometry(seg.image) == image_geometry(image)
    # what the pass found in the frame is mapped back: candidates, choice and landmarks
    np.testing.assert_allclose(
        seg.candidates.voxels.reshape(-1, 3),
        physical_to_voxel(image, seg.candidates.positions.reshape(-1, 3)),
        atol=1e-6,
    )
    chosen = seg.candidates.positions[np.arange(len(seg.mrf.x)), np.asarray(seg.mrf.x)]
    np.testing.assert_allclose(seg.hypotheses[0].chosen, chosen, atol=1e-9)
    # the frame pose takes the first pass's landmarks onto the reference shape
    assert seg.frame_pose.scale > 0 and np.linalg.det(seg.frame_pose.rotation) > 0
    assert "frame" in seg.timings


def test_nibabel_in_nibabel_out(fitted, cohort):
    from medseg.io import to_nibabel

    nii = to_nibabel(cohort[7].load_image())
    seg = fitted.segment(nii)
    assert isinstance(seg.label, nib.Nifti1Image)
    np.testing.assert_allclose(seg.label.affine, nii.affine, atol=1e-6)


def test_same_seed_same_model_whatever_the_jobs(cohort, fitted):
    again = ShapePriorSegmenter(
        n_estimators=6, n_candidates=8, max_iter=100, random_state=0, n_jobs=1
    )
    again.fit(cohort[:6])
    image = cohort[6].load_image()
    # ``fitted`` segments on two threads (its forests' rows split in two blocks, the
    # appearance check's registrations shared out), ``again`` on one
    one, two = again.segment(image), fitted.segment(image)
    assert fitted.detector_.n_jobs == fitted.boundary_.n_jobs == 2
    np.testing.assert_array_equal(one.landmarks, two.landmarks)
    np.testing.assert_array_equal(
        sitk.GetArrayFromImage(one.label), sitk.GetArrayFromImage(two.label)
    )


def test_save_load_round_trip(fitted, saved, cohort):
    loaded = load_model(saved)
    image = cohort[6].load_image()
    a, b = fitted.segment(image), loaded.segment(image)
    np.testing.assert_array_equal(a.landmarks, b.landmarks)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(a.label), sitk.GetArrayFromImage(b.label))
    assert not any(p.suffix == ".pkl" for p in saved.rglob("*"))


def test_tampered_or_foreign_model_files_are_refused(saved, tmp_path):
    copy = shutil.copytree(saved, tmp_path / "copy")
    with open(copy / "template.npz", "r+b") as fh:
        fh.seek(100)
        fh.write(b"\x00\x01\x02")
    with pytest.raises(ModelFileError, match="checksum"):
        load_model(copy)

    future = shutil.copytree(saved, tmp_path / "future")
    meta = json.loads((future / "model.json").read_text())
    meta["format_version"] = 99
    (future / "model.json").write_text(json.dumps(meta))
    with pytest.raises(ModelFileError, match="version 99"):
        load_model(future)

    with pytest.raises(ModelFileError, match="not a medseg model"):
        load_model(tmp_path)


def _as_older_version(saved: Path, folder: Path, version: int) -> Path:
    """A copy of a saved model as medseg wrote it before format ``version + 1``."""
    old = Path(shutil.copytree(saved, folder))
    meta = json.loads((old / "model.json").read_text(encoding="utf-8"))
    stage = sorted(str(p.relative_to(saved)) for p in (saved / "boundary").iterdir())
    dropped = {6: (["appearance.npz"], ["appearance_check"])}
    dropped[5] = (dropped[6][0], dropped[6][1] + ["hypothesis_quantile"])
    dropped[4] = (dropped[5][0] + stage, dropped[5][1] + ["boundary"])
    dropped[3] = (dropped[4][0] + ["frame.npz"], dropped[4][1] + ["frame_passes", "augment_poses"])
    dropped[2] = (
        dropped[3][0] + ["shape_model.npz"],
        dropped[3][1] + ["refine_levels", "n_hypotheses"],
    )
    dropped[1] = (
        dropped[2][0] + ["orientation.npz"],
        dropped[2][1] + ["orientation_weight", "orientation_sigma_mm"],
    )
    files, params = dropped[version]
    for name in files:
        (old / name).unlink()
        meta["checksums"].pop(name)
    if (old / "boundary").is_dir() and version < 5:
        (old / "boundary").rmdir()
    if version < 6 and (old / "shape_model.npz").is_file():  # before 6: no training costs
        header, arrays = load_arrays(old / "shape_model.npz", what="test")
        del arrays["training_costs"]
        save_arrays(old / "shape_model.npz", arrays, header=header | {"format_version": 1})
        meta["checksums"]["shape_model.npz"] = hashlib.sha256(
            (old / "shape_model.npz").read_bytes()
        ).hexdigest()
    for name in params:
        meta["params"].pop(name)
    meta["format_version"] = version
    (old / "model.json").write_text(json.dumps(meta), encoding="utf-8")
    return old


@pytest.mark.parametrize("version", [1, 2, 3, 4])
def test_older_model_versions_still_load_and_run_without_their_missing_parts(
    fitted, saved, cohort, tmp_path, version
):
    loaded = load_model(_as_older_version(saved, tmp_path / "old", version))
    assert loaded.boundary_ is None and not loaded.boundary and not loaded._uses_boundary()
    assert loaded.appearance_ is None
    same = copy.copy(fitted)  # the same model without the parts that version lacks
    same.appearance_check = False
    if version == 4:
        assert loaded.frame_ is not None and loaded.augment_poses == fitted.augment_poses
        image = cohort[6].load_image()
        seg = loaded.segment(image)
        np.testing.assert_array_equal(seg.landmarks, same.segment(image).landmarks)
        np.testing.assert_array_equal(  # the template warped onto the landmarks
            sitk.GetArrayFromImage(seg.label), sitk.GetArrayFromImage(seg.shape_label)
        )
        again = loaded.save(tmp_path / "again")
        meta = json.loads((again / "model.json").read_text(encoding="utf-8"))
        assert meta["format_version"] == 4 and "boundary" not in meta["params"]
        return
    assert loaded.frame_ is None and not loaded._uses_frame()
    assert (loaded.shape_model_ is None) == (version < 3) and (loaded.refine_levels == 0) == (
        version < 3
    )
    assert (loaded.orientation_ is None) == (version == 1)
    assert loaded.augment_poses == 0  # its detectors were trained without posed copies
    image = cohort[6].load_image()
    same.frame_passes = 0
    if version < 3:
        same.refine_levels = 0
    if version == 1:
        same.orientation_weight = 0.0
    np.testing.assert_array_equal(loaded.segment(image).landmarks, same.segment(image).landmarks)
    # saved again, it keeps its version and loads
    again = loaded.save(tmp_path / "again")
    meta = json.loads((again / "model.json").read_text(encoding="utf-8"))
    assert meta["format_version"] == version
    assert load_model(again).frame_ is None


def test_a_version_5_model_solves_every_hypothesis_as_before(fitted, saved, cohort, tmp_path):
    loaded = load_model(_as_older_version(saved, tmp_path / "v5", 5))
    assert loaded.shape_model_.training_costs_ is None and loaded._accept_cost() is None
    assert loaded.boundary_ is not None and loaded.hypothesis_quantile == 0.9  # the default
    always = copy.copy(fitted)
    always.hypothesis_quantile = None
    always.appearance_check = False  # a version 5 model has no appearance check
    image = cohort[6].load_image()
    seg, expected = loaded.segment(image), always.segment(image)
    assert len(seg.hypotheses) == len(expected.hypotheses)
    np.testing.assert_array_equal(seg.landmarks, expected.landmarks)
    again = loaded.save(tmp_path / "again")
    assert json.loads((again / "model.json").read_text(encoding="utf-8"))["format_version"] == 5
    assert json.loads((saved / "model.json").read_text(encoding="utf-8"))["format_version"] == 7


def test_a_version_6_model_loads_without_the_appearance_check(fitted, saved, cohort, tmp_path):
    loaded = load_model(_as_older_version(saved, tmp_path / "v6", 6))
    assert loaded.appearance_ is None and not loaded._uses_appearance()
    loaded.appearance_check = True  # asked for, on a model without the check: ignored
    assert not loaded._uses_appearance()
    unchecked = copy.copy(fitted)
    unchecked.appearance_check = False
    image = cohort[6].load_image()
    seg, expected = loaded.segment(image), unchecked.segment(image)
    assert seg.appearance is None and expected.appearance is None
    np.testing.assert_array_equal(seg.landmarks, expected.landmarks)
    again = loaded.save(tmp_path / "again")
    assert json.loads((again / "model.json").read_text(encoding="utf-8"))["format_version"] == 6
    checked = fitted.segment(image).appearance  # on by default
    assert checked is not None and checked["threshold"] == fitted.appearance_.threshold_
    assert checked["searched"] == (checked["score"] < checked["threshold"])


def test_further_hypotheses_only_when_the_optimum_fits_worse_than_the_training_shapes(
    fitted, cohort
):
    image = cohort[6].load_image()
    always = copy.copy(fitted)
    always.hypothesis_quantile = None
    always.appearance_check = False  # the hypotheses' landmarks, as the MRF chose them
    full = always.segment(image)
    first = full.hypotheses[0]
    assert len(full.hypotheses) > 1

    def with_training_costs(costs):
        model = copy.copy(fitted)
        model.shape_model_ = copy.copy(fitted.shape_model_)
        model.shape_model_.training_costs_ = np.asarray(costs, dtype=float)
        model.appearance_check = False
        return model

    # the refined optimum fits as well as the training shapes: kept alone
    kept = with_training_costs([first.profile_cost]).segment(image)
    assert len(kept.hypotheses) == 1
    np.testing.assert_array_equal(kept.landmarks, first.landmarks)
    # a hair worse than all of them: every hypothesis, as when always solved
    worse = with_training_costs([np.nextafter(first.profile_cost, -np.inf)]).segment(image)
    assert len(worse.hypotheses) == len(full.hypotheses)
    np.testing.assert_array_equal(worse.landmarks, full.landmarks)
    # the quantile picks the threshold among the training costs
    costs = [first.profile_cost - 1.0, first.profile_cost + 1.0]
    picky = with_training_costs(costs)
    picky.hypothesis_quantile = 0.0
    assert len(picky.segment(image).hypotheses) == len(full.hypotheses)
    picky.hypothesis_quantile = 1.0
    assert len(picky.segment(image).hypotheses) == 1
    np.testing.assert_allclose(
        fitted._accept_cost(), np.quantile(fitted.shape_model_.training_costs_, 0.9)
    )


@pytest.mark.parametrize(
    "name", ["orientation.npz", "shape_model.npz", "frame.npz", "boundary/classifier.npz"]
)
def test_current_model_without_one_of_its_files_is_incomplete(saved, tmp_path, name):
    broken = Path(shutil.copytree(saved, tmp_path / "broken"))
    (broken / name).unlink()
    meta = json.loads((broken / "model.json").read_text(encoding="utf-8"))
    meta["checksums"].pop(name)
    (broken / "model.json").write_text(json.dumps(meta), encoding="utf-8")
    with pytest.raises(ModelFileError, match=name):
        load_model(broken)


def test_refinement_keeps_the_mrf_solution_that_fits_the_image_best(fitted, cohort):
    image = cohort[6].load_image()
    fitted = copy.copy(fitted)
    fitted.appearance_check = False  # the landmarks as the hypotheses left them
    seg = fitted.segment(image)
    n = seg.candidates.positions.shape[0]
    first, *others = seg.hypotheses
    assert 1 <= len(seg.hypotheses) <= fitted.n_hypotheses
    np.testing.assert_array_equal(first.labels, np.asarray(seg.mrf.x))  # the MRF's optimum
    for h in others:  # pushed away from the optimum
        assert np.any(h.labels != first.labels)
    best = min(seg.hypotheses, key=lambda h: h.profile_cost)
    np.testing.assert_array_equal(seg.chosen, best.chosen)
    np.testing.assert_array_equal(seg.chosen, seg.candidates.positions[np.arange(n), best.labels])
    expected = fitted.shape_model_.search(image, start=best.chosen, levels=fitted.refine_levels)
    np.testing.assert_array_equal(seg.landmarks, expected.landmarks)
    assert best.profile_cost == pytest.approx(
        fitted.shape_model_.profile_cost(image, seg.landmarks)
    )
    single = copy.copy(fitted)
    single.n_hypotheses = 1
    only = single.segment(image)
    assert len(only.hypotheses) == 1
    np.testing.assert_array_equal(only.landmarks, first.landmarks)
    unrefined = copy.copy(fitted)
    unrefined.refine_levels = 0
    plain = unrefined.segment(image)
    np.testing.assert_array_equal(plain.landmarks, first.chosen)
    assert plain.hypotheses == []
    detection = fitted.segment(image, use_prior=False)  # the baseline is not refined
    np.testing.assert_array_equal(detection.landmarks, detection.chosen)
    bad_values = {
        "refine_levels": (-1, 4, 1.5, True),
        "n_hypotheses": (0, 2.0),
        "hypothesis_quantile": (-0.1, 1.5, True, "0.9"),
        "frame_passes": (-1, 1.0, True),
    }
    for name, bad in [(name, v) for name, values in bad_values.items() for v in values]:
        broken = copy.copy(fitted)
        setattr(broken, name, bad)
        with pytest.raises(ValueError, match=name):
            broken.segment(image)


def test_unfitted_and_too_small(cohort):
    with pytest.raises(NotFittedError):
        ShapePriorSegmenter().segment(cohort[0].load_image())
    with pytest.raises(CohortError, match="at least"):
        ShapePriorSegmenter().fit(cohort[:3])
    with pytest.raises(ValueError, match="orientation_weight"):
        ShapePriorSegmenter(orientation_weight=-1.0).fit(cohort)
    with pytest.raises(ValueError, match="orientation_sigma_mm"):
        ShapePriorSegmenter(orientation_sigma_mm=0.0).fit(cohort)
    with pytest.raises(ValueError, match="refine_levels"):
        ShapePriorSegmenter(refine_levels=5).fit(cohort)
    with pytest.raises(ValueError, match="n_hypotheses"):
        ShapePriorSegmenter(n_hypotheses=0).fit(cohort)


def test_cli_train_then_segment_a_folder(cohort, saved, tmp_path, capsys):
    data = write_cohort(cohort[6:8], tmp_path / "data")
    images = data / "imagesTr"
    out = tmp_path / "out"
    bad = images / "broken_0000.nii.gz"
    bad.write_bytes(b"not a nifti file")

    code = segment_main(
        [
            "-m",
            str(saved),
            "-i",
            str(images),
            "-o",
            str(out),
            "--save-landmarks",
            "mrk.json",
            "--save-surface",
            "vtk",
            "-q",
        ]
    )
    err = capsys.readouterr().err
    assert code == 1  # one bad file: reported, skipped, the others written
    assert "broken_0000.nii.gz" in err and "Traceback" not in err
    for case in cohort[6:8]:
        label = read_image(out / f"{case.case_id}.nii.gz")
        source = read_image(images / f"{case.case_id}_0000.nii.gz")
        assert image_geometry(label) == image_geometry(source)
        assert read_landmarks(out / f"{case.case_id}.mrk.json").shape == (12, 3)
        assert (out / f"{case.case_id}.vtk").is_file()
    assert not (out / "broken.nii.gz").exists()
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["-m", "{model}", "-i", "{missing}", "-o", "{out}"], "does not exist"),
        (["-m", "{tmp}", "-i", "{image}", "-o", "{out}"], "not a medseg model"),
        (["-m", "{model}", "-i", "{flat}", "-o", "{out}"], "3D"),
    ],
)
def test_cli_bad_input_is_one_line_and_nonzero(argv, message, saved, cohort, tmp_path, capsys):
    image = tmp_path / "case.nii.gz"
    sitk.WriteImage(cohort[7].load_image(), str(image))
    flat = tmp_path / "flat.nii.gz"
    sitk.WriteImage(sitk.Image(10, 10, sitk.sitkFloat32), str(flat))
    paths = dict(
        model=saved,
        missing=tmp_path / "nope.nii.gz",
        out=tmp_path / "o.nii.gz",
        tmp=tmp_path,
        image=image,
        flat=flat,
    )
    code = segment_main([a.format(**paths) for a in argv])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and message in err
    assert not (tmp_path / "o.nii.gz").exists()


def test_cli_train_on_a_dataset_folder(cohort, tmp_path, capsys):
    data = write_cohort(cohort[:6], tmp_path / "data")
    code = train_main(
        [
            str(data),
            "-o",
            str(tmp_path / "m"),
            "--landmarks",
            "12",
            "--candidates",
            "6",
            "--seed",
            "3",
            "--orientation-weight",
            "0.5",
            "--refine-levels",
            "1",
            "--hypotheses",
            "3",
            "--frame-passes",
            "2",
            "--augment-poses",
            "1",
            "-q",
        ]
    )
    assert code == 0, capsys.readouterr().err
    assert "trained on 6 of 6 cases" in capsys.readouterr().out
    model = medseg.load_model(tmp_path / "m")
    assert model.landmarks_.shape == (6, 12, 3)
    assert (model.orientation_weight, model.refine_levels, model.n_hypotheses) == (0.5, 1, 3)
    assert model.frame_passes == 2 and model.frame_ is not None
    assert model.augment_poses == 1 and model.detector_.augment_poses == 1


@pytest.mark.parametrize(
    ("flag", "value"),
    [
        ("--refine-levels", "4"),
        ("--hypotheses", "0"),
        ("--orientation-weight", "-1"),
        ("--frame-passes", "-1"),
        ("--augment-poses", "-1"),
    ],
)
def test_cli_train_refuses_a_bad_setting_before_reading(flag, value, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        train_main([str(tmp_path / "no-such-dataset"), "-o", str(tmp_path / "m"), flag, value])
    assert info.value.code == 2
    assert flag in capsys.readouterr().err
    assert not (tmp_path / "m").exists()


def test_segmentation_renders_for_a_notebook(fitted, cohort):
    seg = fitted.segment(cohort[7].load_image())
    figure = seg.plot()
    assert len(figure.axes) == 3
    overlay = figure.axes[-1]
    assert overlay.collections, "the label contour is drawn on the overlay"
    assert overlay.lines, "landmarks near the slice are drawn on the overlay"


def test_one_shared_candidate_is_refined_a_collapse_is_refused():
    """Two landmarks on one candidate (seen on 1 of 199 hippocampus cases) is an ambiguity
    the shape model resolves; landmarks piled on a few positions (a blank image) are not."""
    from medseg.segmenter._hypotheses import collapsed as _collapsed

    rng = np.random.default_rng(0)
    points = rng.normal(size=(12, 3)) * 10
    one_shared = points.copy()
    one_shared[5] = one_shared[4]
    piled = points[rng.integers(0, 8, size=12)]
    flat = points * [1.0, 1.0, 0.0]
    assert not _collapsed(points) and not _collapsed(one_shared)
    assert _collapsed(piled) and _collapsed(flat)


def test_the_check_judges_the_best_shape_of_all_the_searched_starts(fitted, cohort):
    """Every registration the search refines starts a shape search, and the shape that
    correlates best near the structure is judged: here the first start (the best near the
    structure before the shape search) is the found shape tilted by 10 degrees, the second
    the right shape; the found shape is the right one half-turned. Judged alone, the first
    drifted in its shape search to 33 degrees from the found shape and replaced it."""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    image = cohort[6].load_image()
    found = fitted._locate(image)
    right = found.landmarks
    centre = right.mean(axis=0)
    axes = np.linalg.svd(right - centre)[2]  # the shape's principal axes, longest first
    half = Rotation.from_rotvec(np.pi * axes[0]).as_matrix()
    turned = (right - centre) @ half.T + centre
    tilt = Rotation.from_rotvec(np.deg2rad(10.0) * axes[2])
    tilted = (turned - centre) @ tilt.as_matrix().T + centre

    model = copy.copy(fitted)
    model.appearance_ = copy.copy(fitted.appearance_)
    model.appearance_.threshold_ = np.inf  # always search
    model.appearance_.search = lambda *args, **kwargs: np.stack([tilted, right])
    kept, seen = model._check_appearance(image, replace(found, landmarks=turned))
    assert seen["searched"] and seen["replaced"] and seen["turn_deg"] > 150.0
    assert np.linalg.norm(kept.landmarks - right, axis=1).mean() < 1.5
