"""Benchmark of landmark correspondence (medseg.correspondence) and of the shape prior tables.

Phantom: landmarks transferred from the reference case vs the phantom's ground truth. For
each reference landmark the nearest dense site of the reference case
(``meta["surface_points"]``) is found; the same site in another case is the truth. The
landmarks and the truth are both in each case's own world frame, so the subject's pose
(rotation, scale, translation) plays no part in the error.

Hippocampus (MSD Task04, labels 1 + 2 as one structure): every case, fit residuals in mm,
failures, time per case; optionally with mirror alignments allowed (left and right
hippocampi in one cohort).

Shape prior: fit a TripletPrior on the transferred hippocampus landmarks and time the
(C, L, L, L) potential tables.

Usage::

    python benchmarks/bench_correspondence.py --phantom 20 --anisotropic \
        --hippocampus ../shared/data/hippocampus --mirror \
        --n-jobs 2 --out /tmp/bench_corr

Writes ``summary.json`` and PNG figures into ``--out``; prints the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy.spatial import cKDTree

from medseg.correspondence import landmarks_from_labels, plot_correspondences
from medseg.shape import TripletPrior


def _pct(values) -> dict:
    v = np.asarray(values, float)
    return {
        "median": float(np.median(v)),
        "p90": float(np.percentile(v, 90)),
        "max": float(v.max()),
        "mean": float(v.mean()),
    }


def bench_phantom(n_subjects: int, *, anisotropic: bool, n_landmarks: int, n_jobs: int, out: Path):
    from medseg.datasets import make_phantom_cohort

    cohort = make_phantom_cohort(n_subjects, anisotropic=anisotropic, random_state=0)
    labels = [case.load_label() for case in cohort]
    t0 = time.perf_counter()
    res = landmarks_from_labels(
        labels, n_landmarks=n_landmarks, random_state=0, n_jobs=n_jobs,
        case_ids=[c.case_id for c in cohort],
    )  # fmt: skip
    wall = time.perf_counter() - t0
    ref = res.reference_index
    ref_sites = cohort[ref].meta["surface_points"]
    offset, site = cKDTree(ref_sites).query(res.landmarks[ref])
    errors = []
    for s, case in enumerate(cohort):
        if s == ref:
            continue
        truth = case.meta["surface_points"][site]
        errors.append(np.linalg.norm(res.landmarks[s] - truth, axis=1))
    errors = np.concatenate(errors)
    spacing = np.asarray(labels[0].GetSpacing(), float)
    tag = "anisotropic" if anisotropic else "isotropic"
    plot_correspondences(res, out / f"phantom_{tag}.png", n_cases=4)
    return {
        "n_subjects": n_subjects,
        "n_landmarks": res.n_landmarks,
        "spacing_mm": spacing.tolist(),
        "error_mm": _pct(errors),
        "error_voxels_mean_spacing": _pct(errors / spacing.mean()),
        "error_voxels_largest_spacing": _pct(errors / spacing.max()),
        "reference_landmark_to_nearest_site_mm": _pct(offset),
        "residual_mm": _pct(res.residuals_mm[np.arange(len(labels)) != ref]),
        "failed": int(res.failed.sum()),
        "wall_s": wall,
        "s_per_case": wall / len(labels),
    }


def bench_hippocampus(folder: Path, *, allow_reflection: bool, n_jobs: int, out: Path):
    files = sorted((folder / "labelsTr").glob("*.nii.gz"))
    labels = [sitk.ReadImage(str(f)) for f in files]
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    res = landmarks_from_labels(
        labels, labels=(1, 2), random_state=0, n_jobs=n_jobs, allow_reflection=allow_reflection,
        case_ids=[f.name.split(".")[0] for f in files],
    )  # fmt: skip
    wall = time.perf_counter() - t0
    others = np.arange(len(labels)) != res.reference_index
    tag = "mirror" if allow_reflection else "proper"
    plot_correspondences(res, out / f"hippocampus_{tag}.png", n_cases=4)
    worst = np.argsort(res.residuals_mm)[::-1][:5]
    return {
        "n_cases": len(labels),
        "allow_reflection": allow_reflection,
        "n_landmarks": res.n_landmarks,
        "reference": res.case_ids[res.reference_index],
        "residual_mm": _pct(res.residuals_mm[others]),
        "threshold_mm": res.max_residual_mm,
        "failed": [res.case_ids[i] for i in np.flatnonzero(res.failed)],
        "worst": {res.case_ids[i]: float(res.residuals_mm[i]) for i in worst},
        "wall_s": wall,
        "s_per_case": wall / len(labels),
        "main_process_cpu_s": time.process_time() - cpu0,
        "n_jobs": n_jobs,
    }, res


def bench_prior(landmarks: np.ndarray, *, n_candidates=(10, 20, 30)):
    t0 = time.perf_counter()
    prior = TripletPrior(random_state=0).fit(landmarks)
    fit_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    out = {
        "n_shapes": int(landmarks.shape[0]),
        "n_landmarks": int(landmarks.shape[1]),
        "n_cliques": int(len(prior.cliques_)),
        "components": np.bincount(prior.n_components_).tolist(),
        "fit_s": fit_s,
        "tables": [],
    }
    for n_lab in n_candidates:
        cand = landmarks[0][:, None, :] + rng.normal(scale=2.0, size=(landmarks.shape[1], n_lab, 3))
        t0 = time.perf_counter()
        tables = prior.potential_tables(cand)
        out["tables"].append(
            {
                "L": n_lab,
                "MiB": tables.nbytes / 2**20,
                "seconds": time.perf_counter() - t0,
                "finite": bool(np.isfinite(tables).all()),
            }
        )
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--phantom", type=int, default=20, help="phantom subjects (0: skip)")
    parser.add_argument("--anisotropic", action="store_true", help="also a 1x1x2 mm phantom")
    parser.add_argument("--n-landmarks", type=int, default=30, help="phantom landmarks")
    parser.add_argument("--hippocampus", type=Path, default=None, help="MSD Task04 folder")
    parser.add_argument("--mirror", action="store_true", help="also allow_reflection=True")
    parser.add_argument("--n-jobs", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_correspondence"))
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    summary = {"cpu_count": os.cpu_count()}
    if args.phantom:
        summary["phantom"] = bench_phantom(
            args.phantom, anisotropic=False, n_landmarks=args.n_landmarks, n_jobs=args.n_jobs,
            out=args.out,
        )  # fmt: skip
        print(json.dumps({"phantom": summary["phantom"]}, indent=1), flush=True)
        if args.anisotropic:
            summary["phantom_anisotropic"] = bench_phantom(
                args.phantom, anisotropic=True, n_landmarks=args.n_landmarks,
                n_jobs=args.n_jobs, out=args.out,
            )  # fmt: skip
            print(json.dumps({"phantom_anisotropic": summary["phantom_anisotropic"]}, indent=1))
    if args.hippocampus is not None:
        summary["hippocampus"], res = bench_hippocampus(
            args.hippocampus, allow_reflection=False, n_jobs=args.n_jobs, out=args.out
        )
        print(json.dumps({"hippocampus": summary["hippocampus"]}, indent=1), flush=True)
        summary["prior"] = bench_prior(res.landmarks)
        print(json.dumps({"prior": summary["prior"]}, indent=1), flush=True)
        if args.mirror:
            summary["hippocampus_mirror"], _ = bench_hippocampus(
                args.hippocampus, allow_reflection=True, n_jobs=args.n_jobs, out=args.out
            )
            print(json.dumps({"hippocampus_mirror": summary["hippocampus_mirror"]}, indent=1))
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1, sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
