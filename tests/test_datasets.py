"""Cohort discovery (MSD / nnU-Net folders, CSV manifests), write_cohort round trip, errors."""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from medseg.datasets import Case, Cohort, load_cohort, make_phantom_cohort, write_cohort
from medseg.errors import CohortError, InputFileError


@pytest.fixture(scope="module")
def phantom():
    return make_phantom_cohort(3, random_state=2)


@pytest.fixture(scope="module")
def written(phantom, tmp_path_factory):
    return write_cohort(phantom, tmp_path_factory.mktemp("cohorts") / "phantom")


def _tiny(value: int, spacing=(1.0, 1.0, 1.0)) -> tuple[sitk.Image, sitk.Image]:
    array = np.full((4, 5, 6), float(value), dtype=np.float32)
    image = sitk.GetImageFromArray(array)
    image.SetSpacing(spacing)
    label_array = np.zeros((4, 5, 6), dtype=np.uint8)
    label_array[1:3, 1:4, 2:5] = 1
    label = sitk.GetImageFromArray(label_array)
    label.CopyInformation(image)
    return image, label


def _msd_folder(root: Path, case_ids, *, channel: bool, labels=None, training=None) -> Path:
    (root / "imagesTr").mkdir(parents=True)
    (root / "labelsTr").mkdir()
    for k, case_id in enumerate(case_ids):
        image, label = _tiny(k)
        suffix = "_0000" if channel else ""
        sitk.WriteImage(image, str(root / "imagesTr" / f"{case_id}{suffix}.nii.gz"))
        sitk.WriteImage(label, str(root / "labelsTr" / f"{case_id}.nii.gz"))
    spec = {"labels": labels or {"background": 0, "organ": 1}, "file_ending": ".nii.gz"}
    if training is not None:
        spec["training"] = training
    (root / "dataset.json").write_text(json.dumps(spec))
    return root


# ----------------------------------------------------------------------------- real data


@pytest.mark.data
def test_hippocampus_cohort_with_subject_grouping(hippocampus_dir):
    cohort = load_cohort(hippocampus_dir)
    assert len(cohort) == 199
    assert cohort.labels == {"background": 0, "Anterior": 1, "Posterior": 2}
    with open(hippocampus_dir / "subjects.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    expected = {row["case"]: row["subject_key"] for row in rows}
    assert dict(zip(cohort.case_ids, cohort.subjects, strict=True)) == expected
    by_id = {c.case_id: c for c in cohort}
    pairs = [(row["case"], row["paired_case"]) for row in rows if row["paired_case"]]
    assert pairs, "subjects.csv should pair left and right hippocampi"
    for a, b in pairs:
        assert by_id[a].subject == by_id[b].subject
    assert len(set(cohort.subjects)) == len(set(expected.values())) < 199
    # The grouping works with scikit-learn's GroupKFold: no subject on both sides.
    from sklearn.model_selection import GroupKFold

    for train, test in GroupKFold(n_splits=5).split(np.zeros(len(cohort)), groups=cohort.subjects):
        assert not set(cohort.subjects[train]) & set(cohort.subjects[test])
    case = cohort[0]
    image, label = case.load_image(), case.load_label()
    assert image.GetSize() == label.GetSize()
    assert set(np.unique(sitk.GetArrayViewFromImage(label))) <= {0, 1, 2}
    assert case.load_landmarks() is None


# ----------------------------------------------------------------------------- round trip


def test_write_cohort_load_cohort_round_trip(phantom, written):
    assert sorted(p.name for p in written.iterdir()) == [
        "dataset.json",
        "imagesTr",
        "labelsTr",
        "landmarksTr",
        "subjects.csv",
    ]
    assert not [p for p in written.parent.iterdir() if p.name.startswith(".")]  # no leftovers
    spec = json.loads((written / "dataset.json").read_text())
    assert spec["labels"] == {"background": 0, "target": 1}
    assert spec["numTraining"] == 3
    assert (written / "imagesTr" / "phantom_000_0000.nii.gz").is_file()
    loaded = load_cohort(written)
    assert loaded.case_ids == phantom.case_ids
    assert list(loaded.subjects) == list(phantom.subjects)
    assert loaded.labels == phantom.labels
    assert loaded.root == written.resolve()
    for original, case in zip(phantom, loaded, strict=True):
        assert isinstance(case.image, Path) and isinstance(case.landmarks, Path)
        image, label = case.load_image(), case.load_label()
        for a, b in ((original.image, image), (original.label, label)):
            assert a.GetSize() == b.GetSize()
            np.testing.assert_allclose(a.GetSpacing(), b.GetSpacing(), atol=1e-6)
            np.testing.assert_allclose(a.GetOrigin(), b.GetOrigin(), atol=1e-5)
            np.testing.assert_allclose(a.GetDirection(), b.GetDirection(), atol=1e-6)
            assert np.array_equal(sitk.GetArrayViewFromImage(a), sitk.GetArrayViewFromImage(b))
        np.testing.assert_allclose(case.load_landmarks(), original.landmarks, atol=1e-6)


def test_file_matching_without_training_list(written, tmp_path):
    """The same folder without its training list is discovered by file names (_0000)."""
    copy = tmp_path / "copy"
    copy.mkdir()
    for sub in ("imagesTr", "labelsTr", "landmarksTr"):
        (copy / sub).symlink_to(written / sub)
    spec = json.loads((written / "dataset.json").read_text())
    del spec["training"]
    (copy / "dataset.json").write_text(json.dumps(spec))
    loaded = load_cohort(copy)
    assert loaded.case_ids == ["phantom_000", "phantom_001", "phantom_002"]
    assert loaded[1].image.name == "phantom_001_0000.nii.gz"
    assert loaded[1].landmarks.name == "phantom_001.csv"
    assert list(loaded.subjects) == loaded.case_ids  # no subjects.csv: one subject per case


def test_write_cohort_refuses_non_empty_folder(phantom, written, tmp_path):
    before = (written / "dataset.json").read_text()
    with pytest.raises(InputFileError, match="not empty"):
        write_cohort(phantom, written)
    assert (written / "dataset.json").read_text() == before
    # Never over the cohort's own input files, even when asked to overwrite.
    with pytest.raises(InputFileError, match="input file"):
        write_cohort(load_cohort(written), written, overwrite=True)
    # Overwrite replaces a finished folder only once the new one is complete.
    target = tmp_path / "again"
    target.mkdir()
    (target / "stale.txt").write_text("old")
    write_cohort(phantom[:1], target, overwrite=True)
    assert not (target / "stale.txt").exists()
    assert load_cohort(target).case_ids == ["phantom_000"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again"]


def test_write_cohort_failure_leaves_nothing(tmp_path):
    image, label = _tiny(1)
    bad = Cohort(
        cases=[
            Case("a", "s1", image, label),
            Case("b", "s2", image, None),  # no label: fails midway
        ],
        labels={"background": 0, "x": 1},
    )
    with pytest.raises(CohortError, match="'b' has no label"):
        write_cohort(bad, tmp_path / "out")
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- layouts


def test_nnunet_v2_layout_with_channel_suffix(tmp_path):
    root = _msd_folder(tmp_path / "ds", ["b_case", "a_case"], channel=True)
    cohort = load_cohort(root)
    assert cohort.case_ids == ["a_case", "b_case"]
    assert cohort.labels == {"background": 0, "organ": 1}
    assert cohort[0].load_image().GetSize() == (6, 5, 4)
    assert np.all(sitk.GetArrayFromImage(cohort[1].load_image()) == 0)  # b_case was k=0


def test_msd_labels_and_training_list_without_channel(tmp_path):
    root = _msd_folder(
        tmp_path / "ds",
        ["c1", "c2", "c3"],
        channel=False,
        labels={"0": "background", "1": "liver", "2": "tumour"},
        training=[
            {"image": "./imagesTr/c2.nii.gz", "label": "./labelsTr/c2.nii.gz"},
            {"image": "./imagesTr/c1.nii.gz", "label": "./labelsTr/c1.nii.gz"},
        ],
    )
    (root / "subjects.csv").write_text("case,subject_key\nc1,p1\nc2,p1\nc3,p2\n")
    cohort = load_cohort(root)
    assert cohort.labels == {"background": 0, "liver": 1, "tumour": 2}
    assert cohort.case_ids == ["c2", "c1"]  # the training list decides
    assert list(cohort.subjects) == ["p1", "p1"]
    sub = cohort[np.array([1])]
    assert isinstance(sub, Cohort) and sub.case_ids == ["c1"]
    assert cohort[cohort.subjects == "p1"].case_ids == ["c2", "c1"]
    assert cohort[np.array([False, True])].case_ids == ["c1"]
    assert cohort[1:].case_ids == ["c1"] and cohort[-1].case_id == "c1"


def test_csv_manifest(written, tmp_path):
    manifest = tmp_path / "lists" / "cohort.csv"
    manifest.parent.mkdir()
    rel = Path(os.path.relpath(written, manifest.parent))  # relative to the CSV's folder
    with open(manifest, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["image", "label", "subject", "landmarks"])
        for i, subject in enumerate(["s1", "s1", "s2"]):
            w.writerow(
                [
                    rel / "imagesTr" / f"phantom_00{i}_0000.nii.gz",
                    written / "labelsTr" / f"phantom_00{i}.nii.gz",  # absolute also works
                    subject,
                    rel / "landmarksTr" / f"phantom_00{i}.csv" if i < 2 else "",
                ]
            )
    cohort = load_cohort(manifest)
    assert cohort.case_ids == ["phantom_000", "phantom_001", "phantom_002"]
    assert list(cohort.subjects) == ["s1", "s1", "s2"]
    assert cohort.root == manifest.resolve()
    assert cohort[0].image.resolve() == (written / "imagesTr" / "phantom_000_0000.nii.gz").resolve()
    np.testing.assert_allclose(
        cohort[1].load_landmarks(), load_cohort(written)[1].load_landmarks(), atol=0
    )
    assert cohort[2].landmarks is None
    assert cohort[2].load_image().GetSize() == (64, 64, 64)
    # write_cohort's own subjects.csv is itself a valid manifest.
    again = load_cohort(written / "subjects.csv")
    assert again.case_ids == cohort.case_ids and again[0].landmarks is not None


# ----------------------------------------------------------------------------- errors


def _expect(path, match):
    with pytest.raises(CohortError, match=match) as info:
        load_cohort(path)
    return str(info.value)


def test_missing_path(tmp_path):
    message = _expect(tmp_path / "nowhere", "does not exist")
    assert str(tmp_path / "nowhere") in message


def test_missing_labels_folder(tmp_path):
    (tmp_path / "ds" / "imagesTr").mkdir(parents=True)
    assert "labelsTr" in _expect(tmp_path / "ds", "missing folder")


def test_empty_cohort(tmp_path):
    for sub in ("imagesTr", "labelsTr"):
        (tmp_path / "ds" / sub).mkdir(parents=True)
    assert str(tmp_path / "ds") in _expect(tmp_path / "ds", "empty cohort")


def test_image_without_label(tmp_path):
    root = _msd_folder(tmp_path / "ds", ["a", "b"], channel=True)
    (root / "labelsTr" / "b.nii.gz").unlink()
    message = _expect(root, "image without label")
    assert "b_0000.nii.gz" in message


def test_label_without_image(tmp_path):
    root = _msd_folder(tmp_path / "ds", ["a", "b"], channel=False)
    (root / "imagesTr" / "a.nii.gz").unlink()
    message = _expect(root, "1 label.*without an image")
    assert str(root / "labelsTr") in message and "(a)" in message


def test_training_list_names_missing_file(tmp_path):
    root = _msd_folder(
        tmp_path / "ds",
        ["a"],
        channel=False,
        training=[{"image": "./imagesTr/zz.nii.gz", "label": "./labelsTr/a.nii.gz"}],
    )
    assert "zz.nii.gz" in _expect(root, "does not exist")


def test_incomplete_subjects_csv(tmp_path):
    root = _msd_folder(tmp_path / "ds", ["a", "b"], channel=True)
    (root / "subjects.csv").write_text("case,subject_key\na,1\n")
    assert "subjects.csv" in _expect(root, "no subject_key for 1 case")


def test_bad_labels_in_dataset_json(tmp_path):
    root = _msd_folder(tmp_path / "ds", ["a"], channel=True, labels={"whole": [1, 2]})
    assert "dataset.json" in _expect(root, "region-based")


def test_manifest_errors(written, tmp_path):
    image = written / "imagesTr" / "phantom_000_0000.nii.gz"
    label = written / "labelsTr" / "phantom_000.nii.gz"
    cases = {
        "unknown.csv": (f"image,lable\n{image},{label}\n", "unknown manifest column.*lable"),
        "nolabel.csv": (f"image,label\n{image},\n", "image without label"),
        "missing.csv": (f"image,label\n{image},{tmp_path / 'gone.nii.gz'}\n", "does not exist"),
        "empty.csv": ("image,label\n", "empty cohort"),
        "duplicate.csv": (f"image,label\n{image},{label}\n{image},{label}\n", "duplicate"),
    }
    for name, (text, match) in cases.items():
        path = tmp_path / name
        path.write_text(text)
        assert str(path) in _expect(path, match)
    other = tmp_path / "cohort.txt"
    other.write_text("x")
    _expect(other, "not a cohort")
