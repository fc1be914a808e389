"""A corpus of bad inputs, generated here, run end to end through the public entry points.

Every bad file goes through the Python API (``medseg.io`` readers, ``read_mesh``,
``ShapePriorSegmenter.segment``) and through the command-line tools (``medseg-segment``,
``medseg-train``, ``medseg-match``, ``medseg-evaluate``, in process with the file
descriptors captured, and once as a real subprocess). Each must end in one clear
``MedsegError`` naming the file and the problem; on the command line: a non-zero exit code,
exactly one line on stderr, no traceback, and no output written. A hypothesis fuzz test,
bounded in examples and time, mutates valid image and mesh files.
"""

from __future__ import annotations

import functools
import gzip
import re
import struct
import subprocess
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from medseg import io as mio
from medseg.datasets import make_phantom_cohort, write_cohort
from medseg.errors import (
    ImageFormatError,
    ImageGeometryError,
    LabelError,
    LandmarkFileError,
    MedsegError,
    MeshError,
)
from medseg.evaluation.cli import main as evaluate_main
from medseg.inference.cli import main as segment_main
from medseg.inference.match_cli import main as match_main
from medseg.matching import read_mesh, write_mesh
from medseg.segmenter import ShapePriorSegmenter, load_model
from medseg.training.cli import main as train_main

REPO = Path(__file__).resolve().parents[1]
SIZE = 40
N_LANDMARKS = 8


# --------------------------------------------------------------------------- one tiny model


@functools.cache
def _tiny(root: Path) -> tuple[Path, Path]:
    """``(model folder, dataset folder)``: a phantom cohort of 6 and a model fitted on 5.

    Cached per session root, so that this module and test_model_files.py train it once.
    """
    cohort = make_phantom_cohort(
        6, n_landmarks=N_LANDMARKS, size=SIZE, random_state=0, n_surface_points=300
    )
    model = ShapePriorSegmenter(
        n_estimators=3, n_candidates=4, max_iter=30, augment_poses=0, random_state=0
    )  # the inputs are under test, not the detectors: no posed copies (3x the training)
    model.fit(cohort[:5]).save(root / "model")
    write_cohort(cohort, root / "data")
    return root / "model", root / "data"


@pytest.fixture(scope="session")
def tiny(tmp_path_factory) -> tuple[Path, Path]:
    return _tiny(tmp_path_factory.getbasetemp())


@pytest.fixture(scope="session")
def model(tiny):
    return load_model(tiny[0])


# --------------------------------------------------------------------------- file builders


def _volume(shape=(12, 13, 14), dtype=np.float32) -> np.ndarray:
    return (np.random.default_rng(0).random(shape) * 100).astype(dtype)


def _nifti(path: Path, data: np.ndarray, *, header: dict | None = None, dtype=None) -> Path:
    """Write ``data`` as NIfTI-1, then overwrite raw header fields (bypassing nibabel's fixes).

    ``header`` maps ``"pixdim"`` (3 floats), ``"dim"`` (ints), ``"srow"`` ((3, 4) floats),
    ``"qform_code"``, ``"sform_code"`` to the values to store as they are.
    """
    affine = np.diag([1.0, 1.0, 1.0, 1.0])
    raw = path.with_name(path.name.removesuffix(".gz") + ".raw.nii")
    nib.save(nib.Nifti1Image(data, affine, dtype=dtype or data.dtype), raw)
    block = bytearray(raw.read_bytes())
    raw.unlink()
    header = header or {}
    if "dim" in header:
        dims = header["dim"]
        struct.pack_into(f"<{len(dims) + 1}h", block, 40, len(dims), *dims)
    if "pixdim" in header:
        struct.pack_into("<3f", block, 80, *header["pixdim"])
    if "qform_code" in header:
        struct.pack_into("<h", block, 252, header["qform_code"])
    if "sform_code" in header:
        struct.pack_into("<h", block, 254, header["sform_code"])
    if "srow" in header:
        struct.pack_into("<12f", block, 280, *np.asarray(header["srow"], float).ravel())
    path.write_bytes(gzip.compress(bytes(block)) if path.name.endswith(".gz") else bytes(block))
    return path


def _truncated(path: Path) -> Path:
    nib.save(nib.Nifti1Image(_volume((20, 20, 20)), np.eye(4)), path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def _corrupt(path: Path) -> Path:
    nib.save(nib.Nifti1Image(_volume((20, 20, 20)), np.eye(4)), path)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # a flipped byte in the deflate stream
    path.write_bytes(bytes(data))
    return path


def _non_finite(path: Path) -> Path:
    data = _volume()
    data[1, 2, 3] = np.nan
    data[4, 5, 6] = -np.inf
    return _nifti(path, data)


def _singular(path: Path) -> Path:
    srow = np.eye(4)[:3]
    srow[:, 1] = srow[:, 0]  # two parallel voxel axes
    return _nifti(path, _volume(), header={"srow": srow, "sform_code": 1, "qform_code": 0})


def _huge_mha(path: Path) -> Path:
    sitk.WriteImage(sitk.GetImageFromArray(_volume((4, 4, 4))), str(path))
    text = path.read_bytes().replace(b"DimSize = 4 4 4", b"DimSize = 100000 100000 100000")
    path.write_bytes(text)
    return path


# (file name, builder, error class, words the message must contain besides the file name)
BAD_IMAGES = [
    ("truncated.nii.gz", _truncated, ImageFormatError, "truncated"),
    ("corrupt.nii.gz", _corrupt, ImageFormatError, "corrupt"),
    ("not_an_image.nii.gz", lambda p: p.write_bytes(b"\x00" * 7) and p, ImageFormatError, "NIfTI"),
    (
        "zero_spacing.nii.gz",
        lambda p: _nifti(p, _volume(), header={"pixdim": (1.0, 0.0, 1.0)}),
        ImageGeometryError,
        "spacing",
    ),
    (
        "negative_spacing.nii",
        lambda p: _nifti(p, _volume(), header={"pixdim": (1.0, -2.0, 1.0)}),
        ImageGeometryError,
        "spacing",
    ),
    ("singular_direction.nii.gz", _singular, ImageGeometryError, "singular"),
    ("nan_inf_voxels.nii.gz", _non_finite, ImageGeometryError, "NaN or infinite"),
    ("flat_2d.nii.gz", lambda p: _nifti(p, _volume((12, 13))), ImageGeometryError, "2D"),
    ("series_4d.nii.gz", lambda p: _nifti(p, _volume((8, 9, 10, 3))), ImageGeometryError, "4D"),
    ("one_voxel.nii.gz", lambda p: _nifti(p, _volume((1, 1, 1))), ImageGeometryError, "voxel"),
    (
        "huge_declared.nii.gz",
        lambda p: _nifti(p, _volume((4, 4, 4)), header={"dim": (30000, 30000, 30000)}),
        ImageFormatError,
        "truncated",
    ),
    ("huge_declared.mha", _huge_mha, ImageFormatError, "cannot read"),
    (
        "float64_overflow.nii.gz",
        lambda p: _nifti(p, _volume(dtype=np.float64) * 1e306),
        ImageGeometryError,
        "float32",
    ),
]
IMAGE_IDS = [case[0] for case in BAD_IMAGES]


@pytest.fixture(scope="module")
def bad_images(tmp_path_factory) -> dict[str, tuple[Path, type, str]]:
    folder = tmp_path_factory.mktemp("bad_images")
    return {name: (build(folder / name), error, words) for name, build, error, words in BAD_IMAGES}


def _one_line_error(capfd, prog: str) -> str:
    """The single stderr line of a failed CLI run (fd-level: C libraries included)."""
    err = capfd.readouterr().err
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"{prog}: error: "), err
    return lines[0]


def _no_output(folder: Path, name: str) -> None:
    assert not (folder / name).exists()
    assert not [p.name for p in folder.iterdir() if p.name.startswith(".")], "temporary left"


# --------------------------------------------------------------------------- images


@pytest.mark.parametrize("name", IMAGE_IDS)
def test_bad_image_through_the_readers(name, bad_images):
    path, error, words = bad_images[name]
    for read in (mio.read_image, mio.read_label):
        with pytest.raises(error) as info:
            read(path)
        message = str(info.value)
        assert name in message and words in message, message
        assert "\n" not in message


@pytest.mark.parametrize("name", IMAGE_IDS)
def test_bad_image_through_segment_and_its_cli(name, bad_images, model, tiny, tmp_path, capfd):
    path, error, words = bad_images[name]
    with pytest.raises(error, match=words):
        model.segment(path)
    code = segment_main(["-m", str(tiny[0]), "-i", str(path), "-o", str(tmp_path / "o.nii.gz")])
    line = _one_line_error(capfd, "medseg-segment")
    assert code == 2
    assert name in line and words in line
    _no_output(tmp_path, "o.nii.gz")


def test_bad_image_as_a_real_process(bad_images, tiny, tmp_path):
    """The installed entry point's code path in a fresh interpreter: exit 2, one line."""
    path = bad_images["nan_inf_voxels.nii.gz"][0]
    out = tmp_path / "o.nii.gz"
    script = "import sys; from medseg.inference.cli import main; sys.exit(main())"
    argv = [sys.executable, "-c", script, "-m", str(tiny[0]), "-i", str(path), "-o", str(out)]
    done = subprocess.run(argv, capture_output=True, text=True, cwd=REPO, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert "nan_inf_voxels.nii.gz" in done.stderr and "NaN" in done.stderr
    assert not out.exists()


def test_segmenting_a_blank_or_tiny_image_is_an_error_naming_it(tiny, tmp_path, capfd):
    """Coinciding landmarks (nothing to detect) used to crash the spline with a traceback."""
    for name, data in [("blank.nii.gz", np.zeros((30, 30, 30), np.float32)),
                       ("tiny.nii.gz", _volume((2, 2, 2)))]:  # fmt: skip
        path = _nifti(tmp_path / name, data)
        code = segment_main(["-m", str(tiny[0]), "-i", str(path), "-o", str(tmp_path / "o.nrrd")])
        line = _one_line_error(capfd, "medseg-segment")
        assert code == 2 and name in line and "landmarks" in line
        _no_output(tmp_path, "o.nrrd")


@pytest.mark.parametrize("dtype", [np.uint16, np.int16, np.uint8, np.int8])
def test_integer_images_segment_as_their_float_values(dtype, model, tiny):
    """Overflow-prone integer voxel types at their extremes: no integer arithmetic anywhere."""
    image = mio.read_image(Path(tiny[1]) / "imagesTr" / "phantom_005_0000.nii.gz")
    values = sitk.GetArrayFromImage(image).astype(float)
    info = np.iinfo(dtype)
    values = (values - values.min()) / np.ptp(values) * (float(info.max) - info.min) + info.min
    as_int = sitk.GetImageFromArray(np.round(values).astype(dtype))
    as_float = sitk.GetImageFromArray(np.round(values).astype(np.float32))
    for im in (as_int, as_float):
        im.CopyInformation(image)
    got = model.segment(as_int, use_prior=False)
    want = model.segment(as_float, use_prior=False)
    np.testing.assert_array_equal(got.landmarks, want.landmarks)


# --------------------------------------------------------------------------- label maps


BAD_LABELS = [
    ("huge_values.nii.gz", lambda a: (a * 1e30).astype(np.float32), "too large"),
    ("negative.nii.gz", lambda a: -a.astype(np.int8), "negative"),
    ("fractional.nii.gz", lambda a: a.astype(np.float32) * 0.5, "non-integral"),
]


@pytest.mark.parametrize(("name", "make", "words"), BAD_LABELS, ids=[b[0] for b in BAD_LABELS])
def test_bad_label_values(name, make, words, tmp_path):
    mask = np.zeros((12, 13, 14), np.uint8)
    mask[3:8, 4:9, 5:10] = 1
    path = _nifti(tmp_path / name, make(mask))
    with pytest.raises(LabelError, match=words) as info:
        mio.read_label(path)
    assert name in str(info.value)


def _dataset_copy(tiny, tmp_path: Path) -> Path:
    import shutil

    return Path(shutil.copytree(tiny[1], tmp_path / "data"))


def test_train_cli_bad_image_in_the_cohort(tiny, tmp_path, capfd):
    data = _dataset_copy(tiny, tmp_path)
    _non_finite(data / "imagesTr" / "phantom_002_0000.nii.gz")
    code = train_main([str(data), "-o", str(tmp_path / "m"), "-q"])
    line = _one_line_error(capfd, "medseg-train")
    assert code == 2 and "phantom_002_0000.nii.gz" in line and "NaN" in line
    _no_output(tmp_path, "m")


@pytest.mark.parametrize(
    ("name", "text", "words"),
    [
        ("phantom_003.csv", "label,x,y\n0,1,2\n", "lacks column(s) ['z']"),
        ("phantom_003.csv", "label,x,y,z\n0,1,2\n", "line 2: 3 fields"),
        ("phantom_003.fcsv", "# CoordinateSystem = LPS\n1,2.0,3.0\n", "line 2: 3 fields"),
        (
            "phantom_003.mrk.json",
            '{"markups": [{"controlPoints": [{"position": [1, 2]}]}]}',
            "not 3 numbers",
        ),
    ],  # fmt: skip
    ids=["csv-no-z", "csv-short-row", "fcsv-short-row", "mrk-two-coordinates"],
)
def test_landmark_file_missing_columns(name, text, words, tiny, tmp_path, capfd):
    folder = tmp_path / "lm"
    folder.mkdir()
    (folder / name).write_text(text, encoding="utf-8")
    with pytest.raises(LandmarkFileError, match=re.escape(words)):
        mio.read_landmarks(folder / name)
    # the same file inside a training cohort: medseg-train names it
    data = _dataset_copy(tiny, tmp_path)
    for old in (data / "landmarksTr").glob("phantom_003.*"):
        old.unlink()
    (data / "landmarksTr" / name).write_text(text, encoding="utf-8")
    code = train_main([str(data), "-o", str(tmp_path / "m"), "-q"])
    line = _one_line_error(capfd, "medseg-train")
    assert code == 2 and name in line and words in line
    _no_output(tmp_path, "m")


def test_labels_the_cohort_does_not_have(tiny, tmp_path, capfd):
    """--label 3 on label maps holding only 0 and 1: train and evaluate refuse up front."""
    code = evaluate_main([str(tiny[1]), "-o", str(tmp_path / "report"), "--label", "3", "-q"])
    line = _one_line_error(capfd, "medseg-evaluate")
    assert code == 2 and "[3]" in line and "labels present: [1]" in line
    _no_output(tmp_path, "report")
    code = train_main([str(tiny[1]), "-o", str(tmp_path / "m"), "--label", "3", "-q"])
    line = _one_line_error(capfd, "medseg-train")
    assert code == 2 and "[3]" in line and "labels present: [0, 1]" in line
    _no_output(tmp_path, "m")


def test_train_label_error_names_the_label_file(tiny, tmp_path, capfd):
    code = train_main([str(tiny[1]), "-o", str(tmp_path / "m"), "--label", "3", "-q"])
    line = _one_line_error(capfd, "medseg-train")
    assert code == 2 and "phantom_000.nii.gz" in line


# --------------------------------------------------------------------------- meshes


def _tetra_text(suffix: str, vertices, faces) -> str:
    if suffix == ".off":
        head = f"OFF\n{len(vertices)} {len(faces)} 0\n"
        return head + "".join(
            [" ".join(map(str, v)) + "\n" for v in vertices]
            + ["3 " + " ".join(map(str, f)) + "\n" for f in faces]
        )
    if suffix == ".obj":
        return "".join(
            ["v " + " ".join(map(str, v)) + "\n" for v in vertices]
            + ["f " + " ".join(str(i + 1) for i in f) + "\n" for f in faces]
        )
    head = (
        f"ply\nformat ascii 1.0\nelement vertex {len(vertices)}\nproperty float x\n"
        f"property float y\nproperty float z\nelement face {len(faces)}\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    return head + "".join(
        [" ".join(map(str, v)) + "\n" for v in vertices]
        + ["3 " + " ".join(map(str, f)) + "\n" for f in faces]
    )


_V = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
_F = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
BAD_MESHES = [
    ("nan_vertex.off", [[0, 0, 0], ["nan", 0, 0], [0, 1, 0], [0, 0, 1]], _F, "NaN"),
    ("nan_vertex.ply", [[0, 0, 0], [1, 0, 0], [0, "inf", 0], [0, 0, 1]], _F, "NaN or infinite"),
    ("face_out_of_range.off", _V, [*_F[:3], [1, 2, 9]], "face indices"),
    ("face_out_of_range.ply", _V, [*_F[:3], [1, 2, 99]], "face indices"),
    ("face_negative.ply", _V, [*_F[:3], [1, 2, -4]], "face indices"),
    ("face_out_of_range.obj", _V, [*_F[:3], [1, 2, 7]], "face indices"),
]


@pytest.fixture(scope="module")
def good_mesh(tmp_path_factory) -> Path:
    import pyvista as pv

    sphere = pv.Icosphere(nsub=1)
    path = tmp_path_factory.mktemp("mesh") / "sphere.ply"
    write_mesh(path, np.asarray(sphere.points), sphere.faces.reshape(-1, 4)[:, 1:])
    return path


@pytest.mark.parametrize(
    ("name", "vertices", "faces", "words"), BAD_MESHES, ids=[m[0] for m in BAD_MESHES]
)
def test_bad_mesh_through_reader_and_match_cli(
    name, vertices, faces, words, good_mesh, tmp_path, capfd
):
    path = tmp_path / name
    path.write_text(_tetra_text(path.suffix, vertices, faces), encoding="ascii")
    with pytest.raises(MeshError, match=words) as info:
        read_mesh(path)
    assert name in str(info.value)
    for argv in ([str(path), str(good_mesh)], [str(good_mesh), str(path)]):
        code = match_main([*argv, "-o", str(tmp_path / "map.txt"), "-q"])
        line = _one_line_error(capfd, "medseg-match")
        assert code == 2 and name in line and words in line
        _no_output(tmp_path, "map.txt")


@pytest.mark.parametrize("suffix", [".stl", ".vtk", ".ply", ".vtp", ".obj"])
def test_garbage_mesh_file_is_one_quiet_error(suffix, good_mesh, tmp_path, capfd):
    path = tmp_path / f"garbage{suffix}"
    path.write_bytes(np.random.default_rng(1).bytes(300))
    code = match_main([str(path), str(good_mesh), "-o", str(tmp_path / "map.txt"), "-q"])
    line = _one_line_error(capfd, "medseg-match")  # VTK's own messages kept off stderr
    assert code == 2 and path.name in line
    _no_output(tmp_path, "map.txt")


def test_match_cli_names_the_file_of_a_non_manifold_mesh(good_mesh, tmp_path, capfd):
    vertices, faces = read_mesh(good_mesh)
    write_mesh(tmp_path / "two.ply", np.vstack([vertices, vertices + 5]),
               np.vstack([faces, faces + len(vertices)]))  # fmt: skip
    code = match_main([str(good_mesh), str(tmp_path / "two.ply"), "-o", str(tmp_path / "m.txt")])
    line = _one_line_error(capfd, "medseg-match")
    assert code == 2 and "two.ply" in line and "connected components" in line
    _no_output(tmp_path, "m.txt")


# --------------------------------------------------------------------------- fuzzing

_FUZZ = settings(
    max_examples=40,
    deadline=2000,  # ms per example
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@functools.cache
def _seed_files() -> dict[str, bytes]:
    """Valid small files to mutate, built once (in memory)."""
    import tempfile

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        image = sitk.GetImageFromArray(_volume((6, 7, 8)))
        image.SetSpacing((0.8, 1.0, 2.5))
        for name in ("seed.nii", "seed.nii.gz", "seed.mha", "seed.nrrd"):
            out[name] = mio.write_image(image, tmp / name).read_bytes()
        import pyvista as pv

        sphere = pv.Icosphere(nsub=1)
        faces = sphere.faces.reshape(-1, 4)[:, 1:]
        for name in ("seed.off", "seed.ply", "seed.stl", "seed.vtk", "seed.vtp", "seed.obj"):
            write_mesh(tmp / name, np.asarray(sphere.points), faces)
            out[name] = (tmp / name).read_bytes()
    return out


_INT16 = st.integers(-(2**15), 2**15 - 1).map(lambda v: struct.pack("<h", v))
_FLOAT32 = st.floats(width=32).map(lambda v: struct.pack("<f", v))


@st.composite
def _mutations(draw, names: tuple[str, ...]):
    """A seed file with some bytes overwritten, a NIfTI header field set, or truncated."""
    name = draw(st.sampled_from(names))
    data = bytearray(_seed_files()[name])
    if name.endswith(".gz"):
        data = bytearray(gzip.decompress(bytes(data)))
    kind = draw(st.sampled_from(["bytes", "truncate", "header"]))
    if kind == "truncate":
        data = data[: draw(st.integers(0, len(data) - 1))]
    elif kind == "header" and name.startswith("seed.nii"):
        offset = draw(st.sampled_from([40, 42, 44, 46, 70, 72, 76, 80, 84, 88, 108, 252, 254, 280]))
        value = draw(st.one_of(_INT16, _FLOAT32))
        data[offset : offset + len(value)] = value
    else:
        for _ in range(draw(st.integers(1, 8))):
            pos = draw(st.integers(0, len(data) - 1))
            data[pos] = draw(st.integers(0, 255))
    if name.endswith(".gz"):  # a well-formed gzip stream of a broken NIfTI
        data = bytearray(gzip.compress(bytes(data)))
    return name, bytes(data)


@_FUZZ
@given(case=_mutations(("seed.nii", "seed.nii.gz", "seed.mha", "seed.nrrd")))
def test_fuzz_image_reader(case, tmp_path):
    """Mutated image files: a checked 3D image or a MedsegError naming the file, nothing else."""
    name, data = case
    path = tmp_path / name
    path.write_bytes(data)
    try:
        image = mio.read_image(path)
    except MedsegError as exc:
        assert name in str(exc)
        return
    assert image.GetDimension() == 3 and min(image.GetSize()) >= 2
    assert all(s > 0 for s in image.GetSpacing())
    if image.GetPixelID() in (sitk.sitkFloat32, sitk.sitkFloat64):
        assert np.isfinite(sitk.GetArrayViewFromImage(image)).all()


@_FUZZ
@given(case=_mutations(("seed.off", "seed.ply", "seed.stl", "seed.vtk", "seed.vtp", "seed.obj")))
def test_fuzz_mesh_reader(case, tmp_path):
    """Mutated mesh files: finite vertices and in-range faces, or a MeshError naming the file."""
    name, data = case
    path = tmp_path / name
    path.write_bytes(data)
    try:
        vertices, faces = read_mesh(path)
    except MeshError as exc:
        assert name in str(exc)
        return
    assert vertices.ndim == 2 and vertices.shape[1] == 3 and np.isfinite(vertices).all()
    assert faces.shape[1] == 3 and faces.min() >= 0 and faces.max() < len(vertices)


def test_evaluate_cli_refuses_a_manifest_naming_a_bad_image(tiny, tmp_path, capfd):
    """A manifest whose image is a 2D file: evaluation stops before any fold, naming it."""
    data = Path(tiny[1])
    flat = _nifti(tmp_path / "flat.nii.gz", _volume((40, 40)))
    rows = ["image,label,subject"]
    for i in range(6):
        image = flat if i == 2 else data / "imagesTr" / f"phantom_{i:03d}_0000.nii.gz"
        rows.append(f"{image},{data / 'labelsTr' / f'phantom_{i:03d}.nii.gz'},s{i}")
    manifest = tmp_path / "cohort.csv"
    manifest.write_text("\n".join(rows) + "\n", encoding="utf-8")
    code = evaluate_main([str(manifest), "-o", str(tmp_path / "report"), "-q"])
    line = _one_line_error(capfd, "medseg-evaluate")
    assert code == 2 and "flat.nii.gz" in line and "2D" in line
    _no_output(tmp_path, "report")
