"""Tests of medseg.io: image formats, nibabel interop, landmark files, atomic writes, errors."""

from __future__ import annotations

import gzip
import json
import os
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from medseg import io as mio
from medseg.errors import (
    ImageFormatError,
    ImageGeometryError,
    InputFileError,
    LabelError,
    LandmarkFileError,
    ParameterError,
)

FLIP = np.array([-1.0, -1.0, 1.0])  # LPS <-> RAS


def make_image(
    *,
    size=(7, 9, 11),
    spacing=(0.7, 1.3, 2.9),
    origin=(-12.5, 30.25, 7.125),
    angles=(20.0, -35.0, 50.0),
    dtype=np.float32,
    mirror=False,
    seed=0,
) -> sitk.Image:
    """Oblique (rotated direction), anisotropic 3D image with distinct voxel values."""
    rng = np.random.default_rng(seed)
    shape = tuple(reversed(size))
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        values = rng.integers(max(info.min, -1000), min(info.max, 1000), shape, endpoint=True)
    else:
        values = rng.normal(size=shape) * 100
    image = sitk.GetImageFromArray(values.astype(dtype))
    direction = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()
    if mirror:
        direction = direction @ np.diag([1.0, 1.0, -1.0])
    image.SetSpacing(spacing)
    image.SetOrigin(origin)
    image.SetDirection(tuple(direction.ravel()))
    return image


def assert_same_geometry(a: sitk.Image, b: sitk.Image, atol: float = 1e-6) -> None:
    assert a.GetSize() == b.GetSize()
    np.testing.assert_allclose(a.GetSpacing(), b.GetSpacing(), rtol=0, atol=atol)
    np.testing.assert_allclose(a.GetOrigin(), b.GetOrigin(), rtol=0, atol=atol)
    np.testing.assert_allclose(a.GetDirection(), b.GetDirection(), rtol=0, atol=atol)


def listing(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


# --------------------------------------------------------------------------- round trips

FORMATS = [".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd"]


@pytest.mark.parametrize("suffix", FORMATS)
@pytest.mark.parametrize("dtype", [np.float32, np.int16, np.uint8])
def test_round_trip_keeps_geometry_and_voxels(tmp_path, suffix, dtype):
    image = make_image(dtype=dtype)
    path = mio.write_image(image, tmp_path / f"case{suffix}")
    back = mio.read_image(path)
    assert_same_geometry(back, image)
    assert back.GetPixelID() == image.GetPixelID()
    np.testing.assert_array_equal(
        sitk.GetArrayViewFromImage(back), sitk.GetArrayViewFromImage(image)
    )
    assert not [n for n in listing(tmp_path) if n.startswith(".tmp")]


@pytest.mark.parametrize("suffix", [".nii.gz", ".nrrd", ".mha"])
def test_round_trip_mirrored_direction(tmp_path, suffix):
    image = make_image(mirror=True)
    assert np.linalg.det(np.reshape(image.GetDirection(), (3, 3))) < 0
    back = mio.read_image(mio.write_image(image, tmp_path / f"m{suffix}"))
    assert_same_geometry(back, image)


def test_mhd_companion_file_is_renamed_with_its_header(tmp_path):
    image = make_image()
    mio.write_image(image, tmp_path / "vol.mhd")
    names = listing(tmp_path)
    assert names in (["vol.mhd", "vol.zraw"], ["vol.mhd", "vol.raw"])
    header = (tmp_path / "vol.mhd").read_text()
    assert f"ElementDataFile = {names[1]}" in header
    assert_same_geometry(mio.read_image(tmp_path / "vol.mhd"), image)


@pytest.mark.parametrize(
    ("name", "suffix"),
    [
        ("a/B.NII.GZ", ".nii.gz"),
        ("case.001.nii", ".nii"),
        ("x.tar.gz", None),
        ("x.png", None),
        ("slice.dcm", None),  # read-only format
        ("noext", None),
    ],
)
def test_image_suffix(name, suffix):
    assert mio.image_suffix(name) == suffix


def test_sitk_image_passes_through_unchanged():
    image = make_image()
    assert mio.read_image(image) is image


# --------------------------------------------------------------------------- nibabel


def test_to_nibabel_world_positions_agree_with_sitk():
    image = make_image(size=(5, 6, 7))
    nimg = mio.to_nibabel(image)
    assert isinstance(nimg, nib.Nifti1Image)
    data = np.asanyarray(nimg.dataobj)
    array = sitk.GetArrayViewFromImage(image)
    for ijk in [(0, 0, 0), (4, 5, 6), (1, 3, 2), (3, 0, 6)]:
        ras = nimg.affine @ np.r_[ijk, 1.0]
        lps = np.asarray(image.TransformIndexToPhysicalPoint(ijk))
        np.testing.assert_allclose(ras[:3] * FLIP, lps, atol=1e-9)
        assert data[ijk] == array[ijk[::-1]]
    assert nimg.header.get_xyzt_units()[0] == "mm"
    assert nimg.header["qform_code"] == 1 and nimg.header["sform_code"] == 1


def test_read_nibabel_world_positions_agree_with_nibabel():
    rng = np.random.default_rng(1)
    rotation = Rotation.from_euler("zyx", [15.0, 40.0, -25.0], degrees=True).as_matrix()
    affine = np.eye(4)
    affine[:3, :3] = rotation @ np.diag([0.9, 1.7, 3.1])
    affine[:3, 3] = [10.0, -20.0, 35.0]
    data = rng.normal(size=(6, 8, 5)).astype(np.float32)
    nimg = nib.Nifti1Image(data, affine)
    image = mio.read_image(nimg)
    np.testing.assert_allclose(image.GetSpacing(), [0.9, 1.7, 3.1], atol=1e-12)
    array = sitk.GetArrayViewFromImage(image)
    for ijk in [(0, 0, 0), (5, 7, 4), (2, 3, 1)]:
        lps = np.asarray(image.TransformIndexToPhysicalPoint(ijk))
        ras = affine @ np.r_[ijk, 1.0]
        np.testing.assert_allclose(lps, ras[:3] * FLIP, atol=1e-9)
        assert array[ijk[::-1]] == data[ijk]
    # and the medseg helpers agree with both
    zyx = np.array([[1, 3, 2]])
    np.testing.assert_allclose(
        mio.voxel_to_physical(image, zyx)[0] * FLIP, (affine @ np.r_[2, 3, 1, 1.0])[:3], atol=1e-9
    )


def test_nibabel_conversion_agrees_with_itk_nifti_reader(tmp_path):
    """Our affine conversion and ITK's own NIfTI reader give the same geometry."""
    image = make_image(mirror=True)
    nib.save(mio.to_nibabel(image), tmp_path / "n.nii.gz")
    via_itk = mio.read_image(tmp_path / "n.nii.gz")
    via_nib = mio.read_image(nib.load(tmp_path / "n.nii.gz"))
    assert_same_geometry(via_itk, image)
    assert_same_geometry(via_nib, image)
    np.testing.assert_array_equal(
        sitk.GetArrayViewFromImage(via_nib), sitk.GetArrayViewFromImage(image)
    )


def test_big_endian_nifti_through_nibabel(tmp_path):
    data = np.arange(4 * 5 * 6, dtype=">i2").reshape(4, 5, 6)
    nimg = nib.Nifti1Image(data, np.diag([0.5, 1.0, 2.0, 1.0]))
    image = mio.read_image(nimg)
    assert image.GetPixelID() == sitk.sitkInt16
    np.testing.assert_array_equal(sitk.GetArrayViewFromImage(image), data.transpose(2, 1, 0))


def test_nifti2_and_as_input_type(tmp_path):
    image = make_image()
    n2 = nib.Nifti2Image(np.asanyarray(mio.to_nibabel(image).dataobj), mio.to_nibabel(image).affine)
    back = mio.read_image(n2)
    assert_same_geometry(back, image)
    out = mio.as_input_type(back, like=n2)
    assert isinstance(out, nib.Nifti2Image)
    np.testing.assert_allclose(out.affine, n2.affine, atol=1e-9)
    assert mio.as_input_type(back, like=tmp_path / "x.nii.gz") is back
    assert mio.as_input_type(back, like=image) is back


def test_write_image_like_nibabel_writes_same_flavour(tmp_path):
    image = make_image()
    n2 = nib.Nifti2Image(np.asanyarray(mio.to_nibabel(image).dataobj), mio.to_nibabel(image).affine)
    path = mio.write_image(mio.read_image(n2), tmp_path / "out.nii.gz", like=n2)
    assert isinstance(nib.load(path), nib.Nifti2Image)
    assert_same_geometry(mio.read_image(path), image)


@pytest.mark.data
def test_real_hippocampus_image_same_through_itk_and_nibabel(hippocampus_dir):
    path = sorted((hippocampus_dir / "imagesTr").glob("*.nii*"))[0]
    via_itk = mio.read_image(path)
    via_nib = mio.read_image(nib.load(path))
    assert_same_geometry(via_itk, via_nib, atol=1e-5)
    np.testing.assert_allclose(
        sitk.GetArrayViewFromImage(via_itk), sitk.GetArrayViewFromImage(via_nib), rtol=1e-6
    )


@pytest.mark.data
def test_real_hippocampus_labels_match_their_images(hippocampus_dir):
    for path in sorted((hippocampus_dir / "imagesTr").glob("*.nii.gz"))[:5]:
        image = mio.read_image(path)
        label = mio.read_label(hippocampus_dir / "labelsTr" / path.name, reference=image)
        assert label.GetPixelID() in (sitk.sitkUInt8, sitk.sitkInt16, sitk.sitkUInt16)
        assert set(np.unique(sitk.GetArrayViewFromImage(label))) <= {0, 1, 2}
        whole = mio.select_labels(label, (1, 2))
        counts = np.bincount(sitk.GetArrayViewFromImage(label).ravel(), minlength=3)
        assert sitk.GetArrayViewFromImage(whole).sum() == counts[1] + counts[2] > 0


# --------------------------------------------------------------------------- coordinates


@st.composite
def geometries(draw):
    angles = draw(st.tuples(*[st.floats(-180, 180)] * 3))
    spacing = draw(st.tuples(*[st.floats(0.05, 8.0)] * 3))
    origin = draw(st.tuples(*[st.floats(-500, 500)] * 3))
    mirror = draw(st.booleans())
    return angles, spacing, origin, mirror


@settings(max_examples=60, deadline=None)
@given(geometry=geometries(), seed=st.integers(0, 2**32 - 1))
def test_voxel_physical_inverse_on_random_oblique_geometries(geometry, seed):
    angles, spacing, origin, mirror = geometry
    image = make_image(size=(3, 3, 3), spacing=spacing, origin=origin, angles=angles, mirror=mirror)
    rng = np.random.default_rng(seed)
    zyx = rng.uniform(-5, 50, size=(20, 3))
    points = mio.voxel_to_physical(image, zyx)
    # agrees with ITK's own transform ((x, y, z) continuous index)
    for p, idx in zip(points[:3], zyx[:3], strict=True):
        expected = image.TransformContinuousIndexToPhysicalPoint(tuple(idx[::-1]))
        np.testing.assert_allclose(p, expected, atol=1e-9 * (1 + np.abs(expected).max()))
    np.testing.assert_allclose(mio.physical_to_voxel(image, points), zyx, atol=1e-8)
    world = rng.uniform(-800, 800, size=(20, 3))
    np.testing.assert_allclose(
        mio.voxel_to_physical(image, mio.physical_to_voxel(image, world)), world, atol=1e-8
    )
    # shapes: one point in, one point out
    assert mio.voxel_to_physical(image, zyx[0]).shape == (3,)
    assert mio.physical_to_voxel(image, world[0]).shape == (3,)


@settings(max_examples=40, deadline=None)
@given(geometry=geometries())
def test_nibabel_round_trip_on_random_oblique_geometries(geometry):
    angles, spacing, origin, mirror = geometry
    image = make_image(size=(3, 4, 5), spacing=spacing, origin=origin, angles=angles, mirror=mirror)
    nimg = mio.to_nibabel(image)
    ijk = np.array([[0, 0, 0], [2, 3, 4], [1, 0, 3]])
    ras = (nimg.affine @ np.c_[ijk, np.ones(3)].T).T[:, :3]
    lps = mio.voxel_to_physical(image, ijk[:, ::-1])
    np.testing.assert_allclose(ras * FLIP, lps, atol=1e-9 * (1 + np.abs(lps).max()))
    back = mio.read_image(nimg)
    assert_same_geometry(back, image, atol=1e-9 * (1 + np.abs(origin).max()))


# --------------------------------------------------------------------------- landmarks

POINTS = np.array([[-10.5, 20.25, 3.0], [1.0 / 3.0, -7.0, 120.125], [0.0, 0.0, -5.5]])


@pytest.mark.parametrize("suffix", [".csv", ".fcsv", ".mrk.json"])
def test_landmark_round_trip(tmp_path, suffix):
    path = mio.write_landmarks(POINTS, tmp_path / f"lm{suffix}", labels=["a", "b", "c"])
    points, labels = mio.read_landmarks(path, return_labels=True)
    np.testing.assert_array_equal(points, POINTS)
    assert labels == ["a", "b", "c"]


@settings(max_examples=30, deadline=None)
@given(
    points=st.lists(
        st.tuples(*[st.floats(-1e4, 1e4, allow_subnormal=False)] * 3), min_size=1, max_size=8
    ),
    suffix=st.sampled_from([".csv", ".fcsv", ".mrk.json"]),
)
def test_landmark_round_trip_is_exact_for_any_floats(points, suffix):
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = mio.write_landmarks(points, Path(tmp) / f"p{suffix}")
        np.testing.assert_array_equal(mio.read_landmarks(path), np.asarray(points))


def test_written_slicer_files_declare_lps(tmp_path):
    mio.write_landmarks(POINTS, tmp_path / "a.fcsv")
    assert "# CoordinateSystem = LPS" in (tmp_path / "a.fcsv").read_text()
    mio.write_landmarks(POINTS, tmp_path / "a.mrk.json")
    doc = json.loads((tmp_path / "a.mrk.json").read_text())
    assert doc["markups"][0]["coordinateSystem"] == "LPS"
    np.testing.assert_array_equal(doc["markups"][0]["controlPoints"][1]["position"], POINTS[1])


FCSV_BODY = (
    "vtkMRMLMarkupsFiducialNode_0,{0},{1},{2},0,0,0,1,1,1,0,F-1,,vtkMRMLScalarVolumeNode1\n"
    "vtkMRMLMarkupsFiducialNode_1,{3},{4},{5},0,0,0,1,1,1,0,F-2,,vtkMRMLScalarVolumeNode1\n"
)


def _fcsv(system_line: str | None, pts: np.ndarray) -> str:
    head = "# Markups fiducial file version = 4.11\n"
    if system_line is not None:
        head += f"# CoordinateSystem = {system_line}\n"
    head += "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
    return head + FCSV_BODY.format(*pts.ravel())


@pytest.mark.parametrize(
    ("system", "stored"),
    [("LPS", 1.0), ("1", 1.0), ("RAS", FLIP), ("0", FLIP), (None, FLIP)],
)
def test_fcsv_coordinate_system_is_honoured(tmp_path, system, stored):
    lps = POINTS[:2]
    (tmp_path / "s.fcsv").write_text(_fcsv(system, lps * stored))
    points, labels = mio.read_landmarks(tmp_path / "s.fcsv", return_labels=True)
    np.testing.assert_allclose(points, lps, atol=1e-12)
    assert labels == ["F-1", "F-2"]


def _mrk(system: str | None, pts: np.ndarray) -> str:
    markup = {
        "type": "Fiducial",
        "coordinateUnits": "mm",
        "locked": False,
        "labelFormat": "%N-%d",
        "controlPoints": [
            {
                "id": str(i + 1),
                "label": f"F-{i + 1}",
                "description": "",
                "associatedNodeID": "",
                "position": list(p),
                "orientation": [-1.0, -0.0, -0.0, -0.0, -1.0, -0.0, 0.0, 0.0, 1.0],
                "selected": True,
                "locked": False,
                "visibility": True,
                "positionStatus": "defined",
            }
            for i, p in enumerate(pts)
        ],
        "measurements": [],
        "display": {"visibility": True, "opacity": 1.0},
    }
    if system is not None:
        markup["coordinateSystem"] = system
    schema = (
        "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
        "Resources/Schema/markups-schema-v1.0.3.json#"
    )
    return json.dumps({"@schema": schema, "markups": [markup]}, indent=4)


@pytest.mark.parametrize(("system", "stored"), [("LPS", 1.0), ("RAS", FLIP), (None, 1.0)])
def test_mrk_json_coordinate_system_is_honoured(tmp_path, system, stored):
    (tmp_path / "s.mrk.json").write_text(_mrk(system, POINTS * stored))
    np.testing.assert_allclose(mio.read_landmarks(tmp_path / "s.mrk.json"), POINTS, atol=1e-12)


def test_csv_landmarks_any_column_order(tmp_path):
    (tmp_path / "p.csv").write_text("label,z,y,x,extra\nA,3,2,1,foo\n\nB,6,5,4,bar\n")
    points, labels = mio.read_landmarks(tmp_path / "p.csv", return_labels=True)
    np.testing.assert_array_equal(points, [[1, 2, 3], [4, 5, 6]])
    assert labels == ["A", "B"]


@pytest.mark.parametrize(
    ("name", "text", "where"),
    [
        ("nocol.csv", "x,y,label\n1,2,a\n", "line 1"),
        ("count.csv", "x,y,z\n1,2,3\n4,5\n", "line 3"),
        ("nan.csv", "x,y,z\n1,2,3\n4,five,6\n", "line 3"),
        ("inf.csv", "x,y,z\n1,2,inf\n", "line 2"),
        ("empty.csv", "", "empty"),
        ("ijk.fcsv", "# CoordinateSystem = IJK\nn,1,2,3\n", "line 1"),
        ("short.fcsv", "# CoordinateSystem = LPS\nn,1,2\n", "line 2"),
        ("word.fcsv", "# CoordinateSystem = LPS\n\nn,1,2,three,0\n", "line 3"),
        ("bad.mrk.json", '{"markups": [\n{"controlPoints": [}\n]}', "line 2"),
        ("nomarkups.mrk.json", '{"foo": 1}', "markups"),
        ("notobj.mrk.json", '{"markups": [3]}', "markup 0"),
        ("pos.mrk.json", '{"markups": [{"controlPoints": [\n{"position": [1, 2]}]}]}', "line 2"),
    ],
)
def test_bad_landmark_files_name_file_and_line(tmp_path, name, text, where):
    (tmp_path / name).write_text(text)
    with pytest.raises(LandmarkFileError) as info:
        mio.read_landmarks(tmp_path / name)
    assert name in str(info.value)
    assert where in str(info.value)


def test_mrk_json_unplaced_point_and_wrong_count(tmp_path):
    doc = json.loads(_mrk("LPS", POINTS))
    doc["markups"][0]["controlPoints"][2]["positionStatus"] = "undefined"
    (tmp_path / "u.mrk.json").write_text(json.dumps(doc, indent=2))
    with pytest.raises(LandmarkFileError, match="control point 2"):
        mio.read_landmarks(tmp_path / "u.mrk.json")
    (tmp_path / "ok.mrk.json").write_text(_mrk("LPS", POINTS))
    with pytest.raises(LandmarkFileError, match=r"ok\.mrk\.json.*3 points, expected 4"):
        mio.read_landmarks(tmp_path / "ok.mrk.json", n_landmarks=4)


def test_landmark_missing_file_and_unknown_suffix(tmp_path):
    with pytest.raises(InputFileError, match="nope.csv"):
        mio.read_landmarks(tmp_path / "nope.csv")
    (tmp_path / "p.txt").write_text("x,y,z\n1,2,3\n")
    with pytest.raises(LandmarkFileError, match=r"p\.txt.*\.txt"):
        mio.read_landmarks(tmp_path / "p.txt")


# --------------------------------------------------------------------------- bad images


def test_missing_file(tmp_path):
    with pytest.raises(InputFileError, match="absent.nii.gz"):
        mio.read_image(tmp_path / "absent.nii.gz")


def test_unknown_suffix_names_it_and_the_supported_ones(tmp_path):
    (tmp_path / "scan.png").write_bytes(b"\x89PNG")
    with pytest.raises(ImageFormatError) as info:
        mio.read_image(tmp_path / "scan.png")
    message = str(info.value)
    assert "scan.png" in message and "'.png'" in message and ".nii.gz" in message
    with pytest.raises(ImageFormatError, match=r"\.png"):
        mio.write_image(make_image(), tmp_path / "out.png")


@pytest.mark.parametrize("suffix", [".nii.gz", ".nii", ".nrrd", ".mha"])
def test_truncated_file(tmp_path, suffix):
    path = mio.write_image(make_image(size=(20, 20, 20)), tmp_path / f"cut{suffix}")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(ImageFormatError, match=f"cut{suffix}") as info:
        mio.read_image(path)
    assert "Exception thrown" not in str(info.value)  # no raw ITK message


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
def test_nifti_missing_only_the_last_voxel(tmp_path, suffix):
    path = mio.write_image(make_image(dtype=np.int16), tmp_path / f"last{suffix}")
    if suffix == ".nii":
        path.write_bytes(path.read_bytes()[:-2])
    else:
        path.write_bytes(gzip.compress(gzip.decompress(path.read_bytes())[:-2]))
    with pytest.raises(ImageFormatError, match=f"last{suffix}.*truncated"):
        mio.read_image(path)


def test_corrupt_gzip_and_header(tmp_path):
    path = mio.write_image(make_image(), tmp_path / "crc.nii.gz")
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # flip bits in the deflate stream
    path.write_bytes(bytes(data))
    with pytest.raises(ImageFormatError, match="crc.nii.gz"):
        mio.read_image(path)
    (tmp_path / "junk.nii.gz").write_bytes(gzip.compress(b"not a nifti header" * 3))
    with pytest.raises(ImageFormatError, match="junk.nii.gz"):
        mio.read_image(tmp_path / "junk.nii.gz")
    (tmp_path / "junk.mha").write_text("hello\n")
    with pytest.raises(ImageFormatError, match="junk.mha"):
        mio.read_image(tmp_path / "junk.mha")


@pytest.mark.parametrize(
    ("shape", "dims"), [((6, 7), "2D"), ((6, 7, 5, 3), "4D")], ids=["2d", "4d"]
)
def test_not_3d_file(tmp_path, shape, dims):
    nib.save(nib.Nifti1Image(np.zeros(shape, np.float32), np.eye(4)), tmp_path / "d.nii.gz")
    with pytest.raises(ImageGeometryError, match=f"d.nii.gz.*{dims}"):
        mio.read_image(tmp_path / "d.nii.gz")
    with pytest.raises(ImageGeometryError, match=dims):
        mio.read_image(nib.load(tmp_path / "d.nii.gz"))


def test_vector_pixels_and_single_slice(tmp_path):
    vec = sitk.Image([5, 6, 7], sitk.sitkVectorFloat32, 3)
    path = tmp_path / "rgb.mha"
    sitk.WriteImage(vec, str(path))
    with pytest.raises(ImageGeometryError, match="rgb.mha.*component"):
        mio.read_image(path)
    flat = sitk.Image([5, 6, 1], sitk.sitkFloat32)
    with pytest.raises(ImageGeometryError, match="slice"):
        mio.read_image(flat, name="flat.nii")


def test_non_finite_voxels(tmp_path):
    image = make_image()
    array = sitk.GetArrayFromImage(image)
    array[2, 3, 4] = np.nan
    array[0, 0, 1] = np.inf
    bad = sitk.GetImageFromArray(array)
    bad.CopyInformation(image)
    path = mio.write_image(bad, tmp_path / "nan.nrrd")
    with pytest.raises(ImageGeometryError, match=r"nan\.nrrd: 2 voxel\(s\)"):
        mio.read_image(path)


@pytest.mark.parametrize("column", [0, 2])
def test_zero_spacing_or_singular_affine_from_nibabel(column):
    affine = np.diag([1.0, 2.0, 3.0, 1.0])
    affine[:3, column] = 0.0
    nimg = nib.Nifti1Image(np.zeros((4, 5, 6), np.float32), np.eye(4))
    nimg._affine = affine  # nibabel refuses to build a header from it, but files have them
    with pytest.raises(ImageGeometryError, match="spacing"):
        mio.read_image(nimg, name="zero.nii")
    sheared = np.eye(4)
    sheared[:3, 1] = sheared[:3, 0]  # two parallel axes: singular direction
    nimg._affine = sheared
    with pytest.raises(ImageGeometryError, match="singular"):
        mio.read_image(nimg, name="flat.nii")


def test_sheared_affine_is_refused_not_silently_changed(tmp_path):
    affine = np.diag([1.0, 2.0, 3.0, 1.0])
    affine[0, 1] = 0.5  # second voxel axis not perpendicular to the first
    nimg = nib.Nifti1Image(np.ones((4, 5, 6), np.float32), affine)
    with pytest.raises(ImageGeometryError, match="shear.nii.*perpendicular"):
        mio.read_image(nimg, name="shear.nii")
    image = sitk.Image([4, 5, 6], sitk.sitkFloat32)
    image.SetDirection((1.0, 0.3, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))
    with pytest.raises(ImageGeometryError, match="perpendicular"):
        mio.read_image(image)


def test_label_geometry_mismatch_and_tolerance(tmp_path):
    image = make_image()
    label = sitk.Cast(image > 0, sitk.sitkUInt8)
    moved = sitk.Image(label)
    moved.SetOrigin(tuple(np.add(image.GetOrigin(), [0.5, 0, 0])))
    path = mio.write_image(moved, tmp_path / "lab.nii.gz")
    with pytest.raises(LabelError, match=r"lab\.nii\.gz.*origin"):
        mio.read_label(path, reference=image)
    small = sitk.Image(label)
    small.SetSpacing(tuple(np.multiply(image.GetSpacing(), 1 + 2e-5)))
    snapped = mio.read_label(small, reference=image)
    assert snapped.GetSpacing() == image.GetSpacing()
    assert small.GetSpacing() != image.GetSpacing()  # caller's image left alone
    other = make_image(size=(7, 9, 12))
    with pytest.raises(LabelError, match="size"):
        mio.read_label(label, reference=other, name="lab2.nii.gz")


def test_label_pixel_types(tmp_path):
    image = make_image()
    values = (sitk.GetArrayFromImage(image) > 0).astype(np.float32) * 2
    as_float = sitk.GetImageFromArray(values)
    as_float.CopyInformation(image)
    label = mio.read_label(as_float, reference=image)
    assert label.GetPixelID() == sitk.sitkUInt8
    np.testing.assert_array_equal(sitk.GetArrayViewFromImage(label), values)
    fractional = sitk.GetImageFromArray(values * 0.75)
    with pytest.raises(LabelError, match="non-integral"):
        mio.read_label(fractional, name="frac.nii.gz")


def test_select_labels():
    labels = sitk.GetImageFromArray(np.array([[[0, 1, 2, 3]] * 3] * 2, dtype=np.uint8))
    labels.SetSpacing((0.5, 1.0, 2.0))
    mask = mio.select_labels(labels, (1, 2))
    assert mask.GetPixelID() == sitk.sitkUInt8
    np.testing.assert_array_equal(sitk.GetArrayViewFromImage(mask)[0, 0], [0, 1, 1, 0])
    assert mask.GetSpacing() == labels.GetSpacing()
    with pytest.raises(LabelError) as info:
        mio.select_labels(labels, [5, 7])
    assert "[5, 7]" in str(info.value) and "[0, 1, 2, 3]" in str(info.value)


def test_select_labels_empty_label_file_names_the_file(tmp_path):
    empty = sitk.Image([4, 5, 6], sitk.sitkUInt8)
    path = mio.write_image(empty, tmp_path / "blank_seg.nii.gz")
    with pytest.raises(LabelError, match=r"blank_seg\.nii\.gz has none of the labels \[1\]"):
        mio.select_labels(path, 1)


def test_resample_like_label_and_image():
    label = sitk.GetImageFromArray(
        np.random.default_rng(3).integers(0, 4, (8, 9, 10)).astype(np.uint8)
    )
    label.SetSpacing((1.0, 1.5, 2.0))
    reference = make_image(size=(6, 7, 8), spacing=(0.9, 1.1, 1.7), origin=(1.0, 2.0, 3.0))
    out = mio.resample_like(label, reference, is_label=True)
    assert_same_geometry(out, reference, atol=0)
    assert out.GetPixelID() == sitk.sitkUInt8
    assert set(np.unique(sitk.GetArrayViewFromImage(out))) <= {0, 1, 2, 3}
    smooth = mio.resample_like(sitk.Cast(label, sitk.sitkFloat32), label, is_label=False)
    np.testing.assert_allclose(
        sitk.GetArrayViewFromImage(smooth), sitk.GetArrayViewFromImage(label), atol=1e-5
    )


# --------------------------------------------------------------------------- atomic writes


def test_failed_write_leaves_nothing_and_keeps_old_file(tmp_path, monkeypatch):
    image = make_image()
    target = tmp_path / "out.nii.gz"
    target.write_bytes(b"previous result")
    before = listing(tmp_path)

    def partial_then_fail(self, *args, **kwargs):
        Path(self.GetFileName()).write_bytes(b"\x1f\x8b partial")
        raise RuntimeError("disk full")

    monkeypatch.setattr(sitk.ImageFileWriter, "Execute", partial_then_fail)
    with pytest.raises(InputFileError, match="out.nii.gz"):
        mio.write_image(image, target)
    assert listing(tmp_path) == before
    assert target.read_bytes() == b"previous result"


def test_atomic_write_cleans_up_on_any_exception(tmp_path):
    with pytest.raises(KeyError):
        with mio.atomic_write(tmp_path / "a.csv") as tmp:
            assert tmp.parent.parent == tmp_path and tmp.name == "a.csv"
            assert not tmp.parent.name.endswith(".csv")  # a crash leftover matches no glob
            tmp.write_text("half")
            raise KeyError("boom")
    assert listing(tmp_path) == []


def test_refuses_to_overwrite_an_input(tmp_path):
    image = make_image()
    source = mio.write_image(image, tmp_path / "in.nii.gz")
    original = source.read_bytes()
    with pytest.raises(InputFileError, match="in.nii.gz"):
        mio.write_image(image, source, protect=[source])
    alias = tmp_path / "alias.nii.gz"
    alias.symlink_to(source)
    with pytest.raises(InputFileError, match="input"):
        mio.write_image(image, tmp_path / "sub" / ".." / "in.nii.gz", protect=[alias])
    with pytest.raises(InputFileError, match="input"):
        mio.write_image(image, source, like=source)
    assert source.read_bytes() == original
    points = mio.write_landmarks(POINTS, tmp_path / "in.csv")
    with pytest.raises(InputFileError, match="in.csv"):
        mio.write_landmarks(POINTS * 2, points, protect=[str(points)])
    np.testing.assert_array_equal(mio.read_landmarks(points), POINTS)
    assert not (tmp_path / "sub").exists() or listing(tmp_path / "sub") == []


def test_mhd_refuses_to_overwrite_an_input_companion(tmp_path):
    raw = tmp_path / "vol.zraw"
    raw.write_bytes(b"someone's data")
    with pytest.raises(InputFileError, match="vol.zraw"):
        mio.write_image(make_image(), tmp_path / "vol.mhd", protect=[raw])
    assert raw.read_bytes() == b"someone's data"
    assert listing(tmp_path) == ["vol.zraw"]


def test_write_like_checks_output_geometry(tmp_path):
    image = make_image()
    shifted = sitk.Image(image)
    shifted.SetOrigin((0.0, 0.0, 0.0))
    with pytest.raises(ImageGeometryError, match="grid"):
        mio.write_image(shifted, tmp_path / "o.nii.gz", like=image)
    assert listing(tmp_path) == []
    mio.write_image(image, tmp_path / "o.nii.gz", like=image)
    assert os.path.getsize(tmp_path / "o.nii.gz") > 0


# --------------------------------------------------------------------------- DICOM


@pytest.mark.parametrize("dtype", [np.int16, np.uint16, np.uint8])
def test_dicom_series_round_trip(tmp_path, dtype):
    image = make_image(dtype=dtype)
    folder = mio.write_dicom_series(image, tmp_path / "series")
    assert len(listing(folder)) == image.GetSize()[2]
    assert listing(tmp_path) == ["series"]
    back = mio.read_image(folder)
    assert_same_geometry(back, image)
    assert back.GetPixelID() == image.GetPixelID()
    np.testing.assert_array_equal(
        sitk.GetArrayViewFromImage(back), sitk.GetArrayViewFromImage(image)
    )


def test_dicom_series_errors(tmp_path):
    with pytest.raises(ImageFormatError, match="int16"):
        mio.write_dicom_series(make_image(), tmp_path / "f")
    with pytest.raises(ImageGeometryError, match="left-handed"):
        mio.write_dicom_series(make_image(dtype=np.int16, mirror=True), tmp_path / "m")
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "keep.txt").write_text("x")
    with pytest.raises(InputFileError, match="busy"):
        mio.write_dicom_series(make_image(dtype=np.int16), tmp_path / "busy")
    assert listing(tmp_path) == ["busy"]
    with pytest.raises(ImageFormatError, match="busy.*no DICOM series"):
        mio.read_image(tmp_path / "busy")
    # two series in one folder: the caller must choose
    mio.write_dicom_series(make_image(dtype=np.int16, seed=1), tmp_path / "a")
    mio.write_dicom_series(make_image(dtype=np.int16, seed=2), tmp_path / "b")
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for sub in ("a", "b"):
        for f in (tmp_path / sub).iterdir():
            os.link(f, mixed / f"{sub}_{f.name}")
    with pytest.raises(ImageFormatError, match="2 DICOM series"):
        mio.read_image(mixed)
    one = sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(mixed))[0]
    assert mio.read_image(mixed, series_id=one).GetSize() == (7, 9, 11)
    # a single slice file is not a volume
    with pytest.raises(ImageGeometryError, match="slice_0000.dcm.*slice"):
        mio.read_image(tmp_path / "a" / "slice_0000.dcm")


def test_atomic_folder_replaces_on_success_and_keeps_the_old_on_failure(tmp_path):
    from medseg.io import atomic_folder

    target = tmp_path / "model"
    with atomic_folder(target) as staging:
        (staging / "a.txt").write_text("first", encoding="utf-8")
    assert (target / "a.txt").read_text(encoding="utf-8") == "first"

    with pytest.raises(RuntimeError):
        with atomic_folder(target) as staging:
            (staging / "a.txt").write_text("second", encoding="utf-8")
            raise RuntimeError("writer failed")
    assert (target / "a.txt").read_text(encoding="utf-8") == "first"

    with atomic_folder(target) as staging:
        (staging / "b.txt").write_text("third", encoding="utf-8")
    assert sorted(p.name for p in target.iterdir()) == ["b.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["model"]  # no staging or trash left


def _ball(radius_mm: float, *, shape=(36, 36, 36), spacing=(1.0, 1.0, 1.3)) -> sitk.Image:
    """Two nested labels (a ball of label 2 inside a shell of label 1), centred on the grid."""
    zyx = np.indices(shape).reshape(3, -1).T
    mm = (zyx - (np.asarray(shape) - 1) / 2.0) * np.asarray(spacing)[::-1]
    r = np.linalg.norm(mm, axis=1).reshape(shape)
    img = sitk.GetImageFromArray(np.where(r < 0.6 * radius_mm, 2, r < radius_mm).astype(np.uint8))
    img.SetSpacing(spacing)
    return img


def test_label_linear_resampling_follows_a_shape_closer_than_nearest_neighbour():
    """A ball rotated about its centre is the same ball: resampled label-linearly it stays
    closer to the ball drawn on the grid than by nearest neighbour, with no label invented."""
    from medseg.evaluation.metrics import dice

    label = _ball(9.3)
    centre = np.asarray(label.TransformContinuousIndexToPhysicalPoint([17.5] * 3))
    matrix = Rotation.from_rotvec([0.3, -0.5, 0.4]).as_matrix()
    offset = centre - matrix @ centre
    got = {
        how: mio.resample_affine(
            label, matrix, offset, label, is_label=True, label_interpolation=how
        )
        for how in mio.LABEL_INTERPOLATIONS
    }
    scores = {how: dice(img, label) for how, img in got.items()}
    assert scores["linear"] > scores["nearest"] + 0.01, scores
    assert scores["linear"] > 0.97, scores
    for img in got.values():
        assert img.GetPixelID() == label.GetPixelID()
        assert set(np.unique(sitk.GetArrayViewFromImage(img))) == {0, 1, 2}
    # no transform: both give the label back voxel for voxel
    for how in mio.LABEL_INTERPOLATIONS:
        same = mio.resample_like(label, label, is_label=True, label_interpolation=how)
        np.testing.assert_array_equal(sitk.GetArrayViewFromImage(same),
                                      sitk.GetArrayViewFromImage(label))  # fmt: skip
    with pytest.raises(ParameterError, match="label_interpolation"):
        mio.resample_like(label, label, is_label=True, label_interpolation="cubic")


def test_random_pose_moves_the_content_as_it_says_and_stays_within_its_ranges():
    """A blob at ``p`` lies at ``scale * rotation @ p + offset`` in the copy; the angle and
    scale stay within their ranges; the grid grows by the padding; one seed, one copy."""
    size, spacing = 30, (1.0, 1.2, 0.9)
    z, y, x = np.mgrid[:size, :size, :size].astype(float)
    blob = np.exp(-((x - 18) ** 2 + (y - 11) ** 2 + (z - 14) ** 2) / 4.0) * 100
    image = sitk.GetImageFromArray(blob.astype(np.float32))
    image.SetSpacing(spacing)
    image.SetOrigin((5.0, -3.0, 2.0))
    peak = np.asarray(image.TransformContinuousIndexToPhysicalPoint((18.0, 11.0, 14.0)))
    centre = peak + np.array([2.0, -1.0, 3.0])
    angles, scales = [], []
    for seed in range(6):
        moved, rotation, scale, offset = mio.random_pose(
            image, centre, max_angle_deg=90.0, scale_range=(0.8, 1.25), pad_mm=6.0,
            random_state=seed,
        )  # fmt: skip
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        angles.append(np.degrees(Rotation.from_matrix(rotation).magnitude()))
        scales.append(scale)
        expected = scale * rotation @ peak + offset
        np.testing.assert_allclose(scale * rotation @ centre + offset, centre, atol=1e-9)
        arr = sitk.GetArrayFromImage(moved)
        found = moved.TransformIndexToPhysicalPoint(
            [int(v) for v in np.unravel_index(np.argmax(arr), arr.shape)[::-1]]
        )
        assert np.linalg.norm(np.asarray(found) - expected) < 1.3  # within a voxel
        assert np.all(np.asarray(moved.GetSize()) > np.asarray(image.GetSize()))
        again = mio.random_pose(
            image, centre, max_angle_deg=90.0, scale_range=(0.8, 1.25), pad_mm=6.0,
            random_state=seed,
        )  # fmt: skip
        np.testing.assert_array_equal(again[1], rotation)
        assert again[2] == scale
    assert max(angles) <= 90.0 + 1e-9 and 0.8 <= min(scales) and max(scales) <= 1.25
    assert len(set(np.round(scales, 6))) == 6  # the draws differ from seed to seed


@pytest.mark.parametrize("fill", ["zeros", "border"])
def test_content_mask_leaves_out_a_constant_padding_and_the_voxel_beside_it(fill):
    """An image with noise in every voxel is all content; padded with a constant, the
    padding and one voxel on either side of its edge are left out, and nothing else."""
    rng = np.random.default_rng(3)
    image = sitk.GetImageFromArray(rng.normal(50.0, 5.0, size=(9, 11, 13)).astype(np.float32))
    image.SetSpacing((0.8, 1.0, 1.5))
    whole = sitk.GetArrayFromImage(mio.content_mask(image))
    assert whole.dtype == np.uint8 and whole.all()

    padded = mio.resample_affine(
        image, np.eye(3), np.zeros(3), mio.padded_grid(image, 3.0), fill=fill
    )
    mask = sitk.GetArrayFromImage(mio.content_mask(padded))
    pad = np.ceil(3.0 / np.asarray(image.GetSpacing())[::-1] - 1e-9).astype(int)  # (z, y, x)
    expected = np.zeros(mask.shape, dtype=np.uint8)
    inner = tuple(slice(p + 1, p + n - 1) for p, n in zip(pad, (9, 11, 13), strict=True))
    expected[inner] = 1  # the original voxels but their outer layer
    np.testing.assert_array_equal(mask, expected)


def test_content_mask_of_a_constant_image_is_empty_and_of_a_vector_image_refused():
    flat = sitk.Image([6, 6, 6], sitk.sitkFloat32) + 7.0
    assert not sitk.GetArrayFromImage(mio.content_mask(flat)).any()
    with pytest.raises(ParameterError, match="scalar"):
        mio.content_mask(sitk.Image([4, 4, 4], sitk.sitkVectorFloat32, 3))


def test_content_mask_is_its_definition_on_images_with_many_constant_regions():
    """Against the definition written out with SciPy: the values of the voxels whose 3x3x3
    neighbourhood (clipped to the grid) is constant, grown by the 3x3x3 cube, left out."""
    from scipy import ndimage

    rng = np.random.default_rng(11)
    for trial in range(12):
        values = rng.integers(0, 3, size=(8, 10, 12)).astype(np.float32)
        values[:, : rng.integers(0, 5)] = 7.0
        values[rng.integers(0, 6) :, :, :4] = 0.0
        lo = ndimage.minimum_filter(values, 3, mode="nearest")
        flat = ndimage.maximum_filter(values, 3, mode="nearest") == lo
        padding = np.isin(values, values[flat]) if flat.any() else flat
        expected = ~ndimage.binary_dilation(padding, np.ones((3, 3, 3), dtype=bool))
        got = sitk.GetArrayFromImage(mio.content_mask(sitk.GetImageFromArray(values)))
        np.testing.assert_array_equal(got, expected.astype(np.uint8), err_msg=f"trial {trial}")
