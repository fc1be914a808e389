"""Model folders are untrusted input: no code runs on load, forged archives are refused.

The threat is a model folder received from someone else. Its ``model.json`` lists the
SHA-256 of every file, which catches damage, but a forger rewrites ``model.json`` too
(``_reseal`` below does exactly that): every refusal here must then come from the checks on
the archives themselves, made before anything is unpacked. (Plain tampering, a future format
version and a non-model folder are tested in test_model.py.)
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import struct
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import skops.io as sio
from test_bad_inputs import _tiny

from medseg.detection import LandmarkDetector, save_detector
from medseg.errors import InputFileError, ModelFileError
from medseg.inference.cli import main as segment_main
from medseg.io import _archive as _io_archive
from medseg.segmenter import load_model


@pytest.fixture(scope="session")
def tiny(tmp_path_factory) -> tuple[Path, Path]:
    return _tiny(tmp_path_factory.getbasetemp())  # the same model as test_bad_inputs.py


@pytest.fixture
def forged(tiny, tmp_path) -> Path:
    """A copy of the tiny model folder to forge."""
    return Path(shutil.copytree(tiny[0], tmp_path / "model"))


def _reseal(folder: Path) -> None:
    """Recompute the checksums in model.json for the files present, as a forger would."""
    meta = json.loads((folder / "model.json").read_text(encoding="utf-8"))
    meta["checksums"] = {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != "model.json"
    }
    (folder / "model.json").write_text(json.dumps(meta), encoding="utf-8")


def _as_skops(folder: Path) -> Path:
    """Rewrite the model's detector in detector format 1 (skops), as older medseg saved it."""
    detector = LandmarkDetector.load(folder / "detector")
    save_detector(detector, folder / "detector", format_version=1)
    _reseal(folder)
    return folder / "detector" / "forests.skops"


def _rezip(path: Path, members: dict[str, bytes]) -> None:
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)


def _members(path: Path) -> dict[str, bytes]:
    with zipfile.ZipFile(path) as zf:
        return {name: zf.read(name) for name in zf.namelist()}


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=True)
    return buffer.getvalue()


@pytest.fixture
def no_unpacking(monkeypatch):
    """Fail the test if anything reaches np.load or skops' loader."""

    def refuse(*args, **kwargs):
        raise AssertionError("an archive was unpacked before being checked")

    monkeypatch.setattr(np, "load", refuse)
    monkeypatch.setattr(sio, "load", refuse)
    monkeypatch.setattr(sio, "get_untrusted_types", refuse)


# --------------------------------------------------------------------------- no code runs

_UNPICKLING = {"on": False}


def _audit(event: str, args) -> None:
    if event == "pickle.find_class" and _UNPICKLING["on"]:
        raise AssertionError(f"pickle loaded a class or function: {args}")


sys.addaudithook(_audit)  # audit hooks cannot be removed: this one acts only when switched on


def test_loading_never_unpickles(tiny, monkeypatch):
    """Every class or function unpickled anywhere raises an audit event; none may occur."""
    calls = []
    real_load = np.load

    def checked_load(*args, **kwargs):
        calls.append(kwargs.get("allow_pickle"))
        return real_load(*args, **kwargs)

    monkeypatch.setattr(np, "load", checked_load)
    _UNPICKLING["on"] = True
    try:
        model = load_model(tiny[0])
    finally:
        _UNPICKLING["on"] = False
    assert calls and all(flag is False for flag in calls), calls
    assert len(model.detector_.forests_) == model.landmarks_.shape[1]


class _Payload:
    """A class whose restoration would run code: it writes a marker file."""

    marker: Path | None = None

    def __setstate__(self, state):
        Path(state["marker"]).write_text("code ran on load", encoding="utf-8")


def test_model_with_a_skops_detector_still_loads(tiny, forged):
    """Models saved before detector format 2 (forests in skops) load, predicting the same."""
    _as_skops(forged)
    old, new = load_model(forged), load_model(tiny[0])
    X = np.random.default_rng(0).normal(size=(500, new.detector_.n_features_)).astype(np.float32)
    for a, b in zip(old.detector_.forests_, new.detector_.forests_, strict=True):
        assert np.array_equal(a.predict_proba(X), b.predict_proba(X))


def test_skops_file_with_a_foreign_type_is_refused_without_running_it(forged, tmp_path):
    marker = tmp_path / "marker.txt"
    payload = _Payload()
    payload.__dict__["marker"] = str(marker)
    forests = _as_skops(forged)
    original = sio.load(forests, trusted=["sklearn.tree._tree.Tree"])
    sio.dump({"forests": original["forests"], "region": payload}, forests)
    _reseal(forged)
    with pytest.raises(ModelFileError, match="unexpected types") as info:
        load_model(forged)
    assert "_Payload" in str(info.value) and "forests.skops" in str(info.value)
    assert not marker.exists()


def test_skops_file_with_default_trusted_but_foreign_objects_is_refused(forged):
    from sklearn.linear_model import LogisticRegression

    forests = _as_skops(forged)
    original = sio.load(forests, trusted=["sklearn.tree._tree.Tree"])
    sio.dump({"forests": [LogisticRegression()] * len(original["forests"]), "region": None},
             forests)  # fmt: skip
    _reseal(forged)
    with pytest.raises(ModelFileError, match="not scikit-learn forests"):
        load_model(forged)


# --------------------------------------------------------------------------- forged archives


def _set_declared_sizes(path: Path, n_members: int, size: int) -> None:
    """Overwrite the uncompressed size of the first members in the zip's central directory."""
    data = bytearray(path.read_bytes())
    at = 0
    for _ in range(n_members):
        at = data.index(b"PK\x01\x02", at)
        struct.pack_into("<I", data, at + 24, size)
        at += 4
    path.write_bytes(bytes(data))


def test_oversized_archive_is_refused_from_its_directory(forged, no_unpacking):
    _set_declared_sizes(forged / "template.npz", 2, 0xFFFFFFF0)  # 2 x 4.3 GB declared
    _reseal(forged)
    with pytest.raises(ModelFileError, match="refusing to unpack") as info:
        load_model(forged)
    assert "template.npz" in str(info.value) and "8.6 GB" in str(info.value)


def test_archive_limit_is_applied_to_the_whole_model(forged, monkeypatch, no_unpacking):
    sizes = [_io_archive.check_archive(forged / name) for name in
             ("template.npz", "prior.npz", "detector/forests.npz")]  # fmt: skip
    monkeypatch.setattr(_io_archive, "MAX_UNPACKED_BYTES", max(sizes) + 1)
    from medseg.segmenter import _persistence as model_io

    monkeypatch.setattr(model_io, "MAX_UNPACKED_BYTES", sum(sizes) - 1)
    with pytest.raises(ModelFileError, match="archives declare"):
        load_model(forged)


@pytest.mark.parametrize(
    ("forge", "words"),
    [
        ("npy_header_lies", "declares a float64 array of shape (100000, 100000, 100000)"),
        ("object_array", "Python objects"),
        ("truncated", "not a zip archive"),
        ("unsafe_name", "unsafe or duplicate member names"),
        ("huge_directory", "archive directory lists"),
        ("not_npy", "not a valid .npy array"),
    ],
)
def test_forged_template_archive_is_refused_before_unpacking(forge, words, forged, no_unpacking):
    path = forged / "template.npz"
    members = _members(path)
    if forge == "npy_header_lies":
        header = io.BytesIO()
        np.lib.format.write_array_header_1_0(
            header, {"descr": "<f8", "fortran_order": False, "shape": (100000,) * 3}
        )
        members["mask.npy"] = header.getvalue() + b"\x00" * 64
        _rezip(path, members)
    elif forge == "object_array":
        members["landmarks.npy"] = _npy(np.array([{"x": 1}, None], dtype=object))
        _rezip(path, members)
    elif forge == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif forge == "unsafe_name":
        members["../escape.npy"] = members["mask.npy"]
        _rezip(path, members)
    elif forge == "huge_directory":
        data = bytearray(path.read_bytes())
        struct.pack_into("<I", data, data.rindex(b"PK\x05\x06") + 12, 0x7FFFFFFF)
        path.write_bytes(bytes(data))
    elif forge == "not_npy":
        members["mask.npy"] = b"#!/bin/sh\necho not an array\n"
        _rezip(path, members)
    _reseal(forged)
    with pytest.raises(ModelFileError) as info:
        load_model(forged)
    assert "template.npz" in str(info.value) and words in str(info.value), str(info.value)


def test_forged_prior_and_detector_archives_are_refused(forged, no_unpacking):
    for name in ("prior.npz", "detector/forests.npz"):
        copy = Path(shutil.copytree(forged, forged.parent / name.replace("/", "_")))
        _set_declared_sizes(copy / name, 2, 0xFFFFFFF0)
        _reseal(copy)
        with pytest.raises(ModelFileError, match="refusing to unpack") as info:
            load_model(copy)
        assert name.split("/")[-1] in str(info.value)


def test_detector_folder_alone_is_checked_too(forged, no_unpacking):
    _set_declared_sizes(forged / "detector" / "forests.npz", 2, 0xFFFFFFF0)
    with pytest.raises(ModelFileError, match="refusing to unpack"):
        LandmarkDetector.load(forged / "detector")


def test_model_folder_too_large_on_disk_is_refused_before_hashing(forged, monkeypatch):
    big = forged / "template.npz"
    os.truncate(big, 3 * 1024**3)  # sparse: 3 GB declared on disk, nothing written

    def no_hashing(path):
        raise AssertionError(f"hashed {path} before checking the folder's size")

    from medseg.segmenter import _persistence as model_io

    monkeypatch.setattr(model_io, "_sha256", no_hashing)
    with pytest.raises(ModelFileError, match="refusing to load"):
        load_model(forged)


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda meta: meta["params"].update(evil="__import__('os')"), "unknown or malformed"),
        (lambda meta: meta.update(params=["n_landmarks"]), "malformed model parameters"),
    ],
    ids=["unknown-parameter", "parameters-not-a-dict"],
)
def test_forged_model_json_is_refused(edit, words, forged):
    meta = json.loads((forged / "model.json").read_text(encoding="utf-8"))
    edit(meta)
    (forged / "model.json").write_text(json.dumps(meta), encoding="utf-8")
    with pytest.raises(ModelFileError, match=words):
        load_model(forged)


def test_zipped_model_folder_is_not_a_model(tiny, tmp_path):
    archive = shutil.make_archive(str(tmp_path / "model"), "zip", tiny[0])
    with pytest.raises(ModelFileError, match="not a medseg model folder"):
        load_model(archive)
    folder = tmp_path / "m"
    folder.mkdir()
    (folder / "model.json").write_text("{not json", encoding="utf-8")
    with pytest.raises(ModelFileError, match="not valid JSON"):
        load_model(folder)
    with pytest.raises(InputFileError):
        LandmarkDetector.load(tmp_path / "nowhere")


@pytest.mark.parametrize("forge", ["oversized", "foreign-type"])
def test_segment_cli_with_a_forged_model(forge, forged, tiny, tmp_path, capfd):
    if forge == "oversized":
        _set_declared_sizes(forged / "template.npz", 2, 0xFFFFFFF0)
        where = "template.npz"
    else:
        forests = _as_skops(forged)
        original = sio.load(forests, trusted=["sklearn.tree._tree.Tree"])
        sio.dump({"forests": original["forests"], "region": _Payload()}, forests)
        where = "forests.skops"
    _reseal(forged)
    image = Path(tiny[1]) / "imagesTr" / "phantom_005_0000.nii.gz"
    out = tmp_path / "out" / "label.nii.gz"
    code = segment_main(["-m", str(forged), "-i", str(image), "-o", str(out)])
    err = capfd.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and where in err
    assert not out.exists()
