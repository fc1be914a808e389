"""Benchmark the synthetic phantom cohort: build time, write time, and how hard it is.

Usage::

    python benchmarks/bench_phantom.py                 # build / write timings
    python benchmarks/bench_phantom.py --baseline      # + landmark-detection baseline

The baseline is a deliberately plain reference for the later parts, not the package's
detector: per-landmark Random Forests on rotation-invariant voxel features (Gaussian-smoothed
intensity, gradient magnitude and sorted Hessian eigenvalues at 1, 2, 4 and 8 mm, intensities
divided by the image's 99th percentile), trained on the first subjects and tested on the
rest. It reports recall@20 within 2 voxels (a landmark counts as found when one of its 20
best, spatially distinct candidates is within 2 voxels) and the error of the best
candidate alone, overall and on the sites where a neighbour touches the target.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy import ndimage
from skimage.feature import hessian_matrix, hessian_matrix_eigvals, peak_local_max
from sklearn.ensemble import RandomForestClassifier

from medseg.datasets import load_cohort, make_phantom_cohort, write_cohort
from medseg.io import physical_to_voxel


def _timed(label: str, fn, repeat: int = 3):
    """Wall and CPU time (CPU time is what a busy shared machine cannot inflate)."""
    walls, cpus = [], []
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), time.process_time()
        result = fn()
        walls.append(time.perf_counter() - start)
        cpus.append(time.process_time() - start_cpu)
    print(
        f"{label}: wall best {min(walls):.2f} s, median {np.median(walls):.2f} s; "
        f"CPU best {min(cpus):.2f} s ({repeat} runs; load average {os.getloadavg()[0]:.1f})"
    )
    return result


def _features(image: sitk.Image) -> np.ndarray:
    array = sitk.GetArrayFromImage(image).astype(np.float32)
    array /= np.percentile(array, 99)
    spacing = np.asarray(image.GetSpacing())[::-1]
    channels = []
    for sigma_mm in (1.0, 2.0, 4.0, 8.0):
        sigma = sigma_mm / spacing
        smooth = ndimage.gaussian_filter(array, sigma)
        channels.append(smooth)
        channels.append(ndimage.gaussian_gradient_magnitude(array, sigma))
        h = hessian_matrix(smooth, sigma=1e-9, use_gaussian_derivatives=False, order="rc")
        channels.extend(hessian_matrix_eigvals(h) * sigma_mm**2)
    return np.stack(channels, axis=-1)


def baseline(n_subjects: int, n_train: int, random_state: int) -> None:
    cohort = make_phantom_cohort(n_subjects, random_state=random_state)
    feats = [_features(c.image) for c in cohort]
    zyx = [physical_to_voxel(c.image, c.landmarks) for c in cohort]
    n_landmarks = cohort[0].landmarks.shape[0]
    rng = np.random.default_rng(random_state)
    found, best_err, touched = [], [], []
    start = time.perf_counter()
    for k in range(n_landmarks):
        X, y = [], []
        for f, p in zip(feats[:n_train], zyx[:n_train], strict=True):
            grid = np.indices(f.shape[:3]).reshape(3, -1).T
            d = np.linalg.norm(grid - p[k], axis=1)
            pos = grid[d <= 1.5]
            neg = grid[rng.choice(np.flatnonzero(d > 3.0), 1500, replace=False)]
            near = grid[np.flatnonzero((d > 3.0) & (d < 10.0))]
            neg = np.vstack([neg, near[rng.choice(len(near), 500, replace=False)]])
            for pts, lab in ((pos, 1), (neg, 0)):
                X.append(f[tuple(pts.T)])
                y.append(np.full(len(pts), lab))
        forest = RandomForestClassifier(
            n_estimators=40, min_samples_leaf=3, n_jobs=2, random_state=random_state
        ).fit(np.vstack(X), np.concatenate(y))
        for case, f, p in zip(cohort[n_train:], feats[n_train:], zyx[n_train:], strict=True):
            prob = forest.predict_proba(f.reshape(-1, f.shape[-1]))[:, 1].reshape(f.shape[:3])
            prob = ndimage.gaussian_filter(prob, 1.0)
            peaks = peak_local_max(prob, min_distance=3, num_peaks=20, exclude_border=False)
            dist = np.linalg.norm(peaks - p[k], axis=1)
            found.append(dist.min() <= 2.0)
            best_err.append(dist[0])
            touched.append(case.meta["contact"][case.meta["landmark_index"][k]])
    found, best_err, touched = map(np.asarray, (found, best_err, touched))
    print(
        f"baseline ({n_train} train / {n_subjects - n_train} test subjects, {n_landmarks} "
        f"landmarks, {time.perf_counter() - start:.0f} s): recall@20 within 2 voxels "
        f"{found.mean():.3f} (touched sites {found[touched].mean():.3f}, free sites "
        f"{found[~touched].mean():.3f}); top-1 error median {np.median(best_err):.1f} voxels, "
        f"top-1 within 2 voxels {np.mean(best_err <= 2.0):.3f}; "
        f"{touched.mean():.0%} of landmark instances on touched sites"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", action="store_true", help="run the detection baseline")
    parser.add_argument("--n-subjects", type=int, default=20)
    args = parser.parse_args()

    make_phantom_cohort(1, random_state=0)  # warm-up (imports, caches)
    for kwargs in ({}, {"anisotropic": True, "oblique": True}):
        name = ", ".join(f"{k}={v}" for k, v in kwargs.items()) or "isotropic 1 mm, 64^3"
        cohort = _timed(
            f"make_phantom_cohort({args.n_subjects}) [{name}]",
            lambda kwargs=kwargs: make_phantom_cohort(args.n_subjects, random_state=0, **kwargs),
        )
    tracemalloc.start()
    make_phantom_cohort(args.n_subjects, random_state=0)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    print(f"peak traced memory while building {args.n_subjects} subjects: {peak / 2**20:.0f} MiB")
    with tempfile.TemporaryDirectory() as tmp:
        counter = iter(range(100))
        folder = _timed(
            f"write_cohort({args.n_subjects})",
            lambda: write_cohort(cohort, Path(tmp) / f"c{next(counter)}"),
        )
        size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
        print(f"on disk: {size / 2**20:.1f} MiB")
        _timed(
            "load_cohort + read every image and label",
            lambda: [(c.load_image(), c.load_label()) for c in load_cohort(folder)],
        )
    if args.baseline:
        baseline(args.n_subjects, n_train=args.n_subjects * 3 // 4, random_state=0)


if __name__ == "__main__":
    main()
