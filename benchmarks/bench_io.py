"""Cost of medseg.io's checks over plain SimpleITK, and a pass over the real cohort.

Measures
--------
1. A large volume (default 256^3 float32, oblique) written and read as .nii.gz, .nii,
   .nrrd and .mha: ``medseg.io.write_image`` / ``read_image`` against ``sitk.WriteImage`` /
   ``sitk.ReadImage`` (median of ``--repeat`` runs, the two alternating). The extra read
   cost is the NIfTI header/truncation check (gzip trailer) and the non-finite voxel check;
   the extra write cost is the atomic rename.
2. The hippocampus cohort (``MEDSEG_DATA`` or ../shared/data): every image and label read
   with ``read_image`` / ``read_label(label, reference=image)``; reports time, failures and
   how many labels needed their geometry snapped to the image (within 1e-4).

Usage::

    python benchmarks/bench_io.py [--size 256] [--repeat 3] [--tmp /tmp]

Writes only to a temporary folder under ``--tmp``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from medseg import io as mio
from medseg.errors import MedsegError


def _paired_median(fn_a, fn_b, repeat: int) -> tuple[float, float]:
    """Median times of two functions, run alternately so machine load hits both alike."""
    times_a, times_b = [], []
    for _ in range(repeat):
        for fn, times in ((fn_a, times_a), (fn_b, times_b)):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
    return statistics.median(times_a), statistics.median(times_b)


def bench_large(size: int, repeat: int, tmp: Path) -> None:
    rng = np.random.default_rng(0)
    image = sitk.GetImageFromArray(rng.normal(size=(size, size, size)).astype(np.float32))
    image.SetSpacing((0.8, 0.9, 1.5))
    angle = np.deg2rad(25.0)
    c, s = np.cos(angle), np.sin(angle)
    image.SetDirection((c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0))
    mb = image.GetNumberOfPixels() * 4 / 1e6
    print(f"volume {size}^3 float32 ({mb:.0f} MB), median of {repeat}")
    print(f"{'format':8s} {'sitk write':>11s} {'io write':>9s} {'sitk read':>10s} {'io read':>8s}")
    for suffix in (".nii.gz", ".nii", ".nrrd", ".mha"):
        plain = tmp / f"plain{suffix}"
        ours = tmp / f"ours{suffix}"
        compress = suffix != ".nii"
        w_sitk, w_io = _paired_median(
            lambda p=plain, c=compress: sitk.WriteImage(image, str(p), c),
            lambda p=ours: mio.write_image(image, p),
            repeat,
        )
        r_sitk, r_io = _paired_median(
            lambda p=plain: sitk.ReadImage(str(p)), lambda p=ours: mio.read_image(p), repeat
        )
        print(f"{suffix:8s} {w_sitk:10.2f}s {w_io:8.2f}s {r_sitk:9.2f}s {r_io:7.2f}s")


def bench_cohort(root: Path) -> None:
    folder = root / "hippocampus"
    images = sorted((folder / "imagesTr").glob("*.nii.gz"))
    if not images:
        print(f"hippocampus cohort not found under {root}: skipped")
        return
    failures, labels = [], {}
    t0 = time.perf_counter()
    for path in images:
        try:
            image = mio.read_image(path)
            labels[path.name] = mio.read_label(folder / "labelsTr" / path.name, reference=image)
        except MedsegError as exc:
            failures.append(f"{path.name}: {exc}")
    elapsed = time.perf_counter() - t0
    snapped = sum(
        mio.image_geometry(sitk.ReadImage(str(folder / "labelsTr" / name)))
        != mio.image_geometry(label)
        for name, label in labels.items()
    )
    t0 = time.perf_counter()
    for path in images:
        sitk.ReadImage(str(path))
        sitk.ReadImage(str(folder / "labelsTr" / path.name))
    plain = time.perf_counter() - t0
    print(f"hippocampus: plain sitk.ReadImage of the same pairs: {plain:.2f}s")
    print(
        f"hippocampus: {len(images)} image+label pairs read and checked in {elapsed:.2f}s "
        f"({1000 * elapsed / len(images):.1f} ms/case); {len(failures)} failures; "
        f"{snapped} labels had geometry within tolerance but not identical (snapped)"
    )
    for line in failures[:10]:
        print("  ", line)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--size", type=int, default=256, help="Edge of the cube; 0 skips. Default: 256."
    )
    parser.add_argument("--repeat", type=int, default=3, help="Runs per timing. Default: 3.")
    parser.add_argument("--tmp", default=tempfile.gettempdir(), help="Scratch folder root.")
    args = parser.parse_args()
    data = Path(os.environ.get("MEDSEG_DATA", Path(__file__).resolve().parents[2] / "shared/data"))
    if args.size > 0:
        with tempfile.TemporaryDirectory(dir=args.tmp) as tmp:
            bench_large(args.size, args.repeat, Path(tmp))
    bench_cohort(data)


if __name__ == "__main__":
    main()
