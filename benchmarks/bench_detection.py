"""Benchmark of medseg.detection: accuracy on the phantom and hippocampus cohorts, speed, memory.

Usage::

    python benchmarks/bench_detection.py phantom      [--n-jobs 2] [--out /tmp/det_phantom.json]
    python benchmarks/bench_detection.py hippocampus  [--data ../shared/data] [--n-train 60]
    python benchmarks/bench_detection.py scaling      [--sizes 64 128 192] [--n-landmarks 40]

* ``phantom``: ``make_phantom_cohort(20, random_state=0)``, train on subjects 0-11, test on
  12-19 (random poses); recall@L (L = 20) within 2 voxels, top-1 candidate error, the
  fraction of candidates on the target's boundary, fit and prediction time, for the
  per-landmark forests and the single multi-class forest.
* ``hippocampus``: the MSD cohort, a subject-grouped split (``GroupShuffleSplit`` on the
  ``subject_key`` of ``subjects.csv``); landmarks in correspondence from
  ``medseg.correspondence.landmarks_from_labels`` (labels 1 and 2), or with ``--stand-in``
  the 6 extreme points of the label along the image axes plus its centroid; per-landmark
  recall@20 within 2 voxels and top-1 error.
* ``scaling``: a detector with ``--n-landmarks`` landmarks trained on 64 mm phantoms, then
  one test phantom of each size: feature time, prediction time (scoring, suppression,
  refinement), peak traced memory (tracemalloc: numpy buffers) and the process's peak RSS.

Figures go to stdout as JSON (and to ``--out``). Nothing is written into the repository.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

from medseg.detection import LandmarkDetector, compute_features

REPO = Path(__file__).resolve().parents[1]


def _summary(hits: np.ndarray, top1: np.ndarray, top1_vox: np.ndarray) -> dict:
    return {
        "recall_at_20_within_2_voxels": float(np.nanmean(hits)),
        "top1_error_mm_mean": float(np.nanmean(top1)),
        "top1_error_mm_median": float(np.nanmedian(top1)),
        "top1_error_voxels_median": float(np.nanmedian(top1_vox)),
        "top1_within_2_voxels": float(np.nanmean(top1_vox <= 2.0)),
    }


def _boundary_distance(label) -> np.ndarray:
    """Distance (mm) of every voxel to the boundary of the label's foreground."""
    import SimpleITK as sitk

    mask = sitk.Cast(label > 0, sitk.sitkUInt8)
    signed = sitk.SignedMaurerDistanceMap(mask, squaredDistance=False, useImageSpacing=True)
    return np.abs(sitk.GetArrayFromImage(signed))


def _evaluate(det, images, landmarks, *, labels=None, n_candidates=20, stride=2) -> dict:
    """Recall and top-1 error; with ``labels``, also where the candidates lie.

    ``candidates_on_target_boundary``: the fraction of all candidates within 2 voxels of
    the target's boundary. Candidates elsewhere sit on look-alike structures (the phantom's
    neighbours and distractors), not on a wrong point of the right boundary.
    """
    hits, top1, top1_vox, times, on_boundary = [], [], [], [], []
    for k, (image, lms) in enumerate(zip(images, landmarks, strict=True)):
        t0 = time.perf_counter()
        cs = det.candidates(image, n_candidates=n_candidates, stride=stride)
        times.append(time.perf_counter() - t0)
        voxel = float(max(image.GetSpacing()))
        hits.append(cs.recall(lms, radius_mm=2.0 * voxel))
        d = cs.distances(lms)[:, 0]
        top1.append(d)
        top1_vox.append(d / voxel)
        if labels is not None:
            dist = _boundary_distance(labels[k])
            vox = np.clip(np.rint(cs.voxels).astype(int), 0, np.array(dist.shape) - 1)
            on_boundary.append(np.mean(dist[vox[..., 0], vox[..., 1], vox[..., 2]] <= 2 * voxel))
    hits, top1, top1_vox = np.array(hits), np.array(top1), np.array(top1_vox)
    out = _summary(hits, top1, top1_vox)
    if on_boundary:
        out["candidates_on_target_boundary"] = float(np.mean(on_boundary))
    out["per_landmark_recall"] = np.round(np.nanmean(hits, axis=0), 3).tolist()
    out["per_landmark_top1_mm_median"] = np.round(np.nanmedian(top1, axis=0), 2).tolist()
    out["candidates_seconds_per_image"] = float(np.mean(times))
    return out


def bench_phantom(args) -> dict:
    from medseg.datasets import make_phantom_cohort

    cohort = make_phantom_cohort(20, n_landmarks=args.n_landmarks, random_state=0)
    images = [c.load_image() for c in cohort]
    lms = [c.load_landmarks() for c in cohort]
    labels = [c.load_label() for c in cohort]
    result = {"cohort": "phantom", "n_train": 12, "n_test": 8, "n_landmarks": args.n_landmarks}
    for mode in args.modes:
        det = LandmarkDetector(mode=mode, random_state=0, n_jobs=args.n_jobs, **args.detector)
        t0 = time.perf_counter()
        c0 = time.process_time()
        det.fit(images[:12], lms[:12])
        fit = {"fit_seconds": time.perf_counter() - t0, "fit_cpu_seconds": time.process_time() - c0}
        res = _evaluate(det, images[12:], lms[12:], labels=labels[12:], stride=args.stride)
        res.update(fit)
        res["params"] = {k: str(v) for k, v in det.get_params().items()}
        result[mode] = res
        print(json.dumps({mode: {k: v for k, v in res.items() if "per_" not in k}}), flush=True)
    return result


def _stand_in_landmarks(label) -> np.ndarray:
    """Extreme points of the label along the image axes, and its centroid (mm)."""
    import SimpleITK as sitk

    from medseg.io import voxel_to_physical

    arr = sitk.GetArrayViewFromImage(label) > 0
    zyx = np.argwhere(arr)
    pts = []
    for ax in range(3):
        for pick in (np.argmin, np.argmax):
            extreme = zyx[zyx[:, ax] == zyx[pick(zyx[:, ax]), ax]]
            pts.append(extreme.mean(axis=0))
    pts.append(zyx.mean(axis=0))
    return voxel_to_physical(label, np.array(pts))


def bench_hippocampus(args) -> dict:
    from sklearn.model_selection import GroupShuffleSplit

    from medseg.datasets import load_cohort

    root = Path(args.data) / "hippocampus"
    cohort = load_cohort(root)
    groups = np.asarray(cohort.subjects)
    split = GroupShuffleSplit(n_splits=1, test_size=0.2, random_state=0)
    train, test = next(split.split(np.zeros(len(groups)), groups=groups))
    train = train[: args.n_train]
    test = test[: args.n_test]
    if set(groups[train]) & set(groups[test]):
        raise RuntimeError("subject-grouped split leaked a subject into both sides")
    images = {i: cohort[int(i)].load_image() for i in np.r_[train, test]}
    labels = {i: cohort[int(i)].load_label() for i in np.r_[train, test]}
    t0 = time.perf_counter()
    if args.stand_in:
        lms = {i: _stand_in_landmarks(labels[i]) for i in labels}
        source = "stand-in: 6 axis-extreme points of labels 1+2 and the centroid"
    else:
        from medseg.correspondence import landmarks_from_labels

        order = list(np.r_[train, test])
        res = landmarks_from_labels(
            [labels[i] for i in order],
            n_landmarks=args.n_landmarks,
            labels=(1, 2),
            random_state=0,
            n_jobs=args.n_jobs,
            keep_largest=True,
        )
        lms = {i: res.landmarks[k] for k, i in enumerate(order)}
        failed = {i for k, i in enumerate(order) if res.failed[k]}
        train = np.array([i for i in train if i not in failed])
        test = np.array([i for i in test if i not in failed])
        source = "medseg.correspondence.landmarks_from_labels(labels=(1, 2))"
    landmark_time = time.perf_counter() - t0
    result = {
        "cohort": "hippocampus",
        "landmarks": source,
        "landmark_seconds": landmark_time,
        "n_train_cases": int(len(train)),
        "n_test_cases": int(len(test)),
        "n_train_subjects": int(len(set(groups[train]))),
        "n_test_subjects": int(len(set(groups[test]))),
    }
    for mode in args.modes:
        det = LandmarkDetector(mode=mode, random_state=0, n_jobs=args.n_jobs, **args.detector)
        t0 = time.perf_counter()
        det.fit([images[i] for i in train], [lms[i] for i in train])
        fit_s = time.perf_counter() - t0
        res = _evaluate(det, [images[i] for i in test], [lms[i] for i in test], stride=1)
        res["fit_seconds"] = fit_s
        result[mode] = res
        print(json.dumps({mode: {k: v for k, v in res.items() if "per_" not in k}}), flush=True)
    return result


def bench_scaling(args) -> dict:
    from medseg.datasets import make_phantom_cohort

    train = make_phantom_cohort(12, n_landmarks=args.n_landmarks, random_state=0)
    det = LandmarkDetector(random_state=0, n_jobs=args.n_jobs, **args.detector)
    t0 = time.perf_counter()
    det.fit([c.load_image() for c in train], [c.load_landmarks() for c in train])
    result = {"n_landmarks": args.n_landmarks, "fit_seconds": time.perf_counter() - t0, "sizes": {}}
    for size in args.sizes:
        case = make_phantom_cohort(1, n_landmarks=args.n_landmarks, size=size, random_state=99)[0]
        image = case.load_image()
        tracemalloc.start()
        t0, c0 = time.perf_counter(), time.process_time()
        feats = compute_features(image, det.features)
        t_feat, c_feat = time.perf_counter() - t0, time.process_time() - c0
        _, peak_feat = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        t0, c0 = time.perf_counter(), time.process_time()
        cs = det.candidates(image, n_candidates=20, stride=args.stride, precomputed=feats)
        t_cand, c_cand = time.perf_counter() - t0, time.process_time() - c0
        _, peak_cand = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        del feats
        entry = {
            "voxels": int(np.prod(image.GetSize())),
            "features_seconds": t_feat,
            "candidates_seconds": t_cand,
            "candidates_breakdown": cs.meta["timings"],
            "total_seconds": t_feat + t_cand,
            "features_cpu_seconds": c_feat,
            "candidates_cpu_seconds": c_cand,
            "load_average": os.getloadavg()[0],
            "peak_traced_MiB_features": peak_feat / 2**20,
            "peak_traced_MiB_candidates": peak_cand / 2**20,
            "process_peak_rss_MiB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "recall_at_20_within_2_voxels": float(
                np.mean(cs.recall(case.load_landmarks(), radius_mm=2.0))
            ),
        }
        result["sizes"][str(size)] = entry
        print(json.dumps({size: entry}), flush=True)
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=["phantom", "hippocampus", "scaling"])
    parser.add_argument("--n-jobs", type=int, default=2, help="forest threads (default 2)")
    parser.add_argument("--modes", nargs="+", default=["per_landmark", "multiclass"])
    parser.add_argument("--n-landmarks", type=int, default=None, help="default 30 / 40 / auto")
    parser.add_argument("--stride", type=int, default=2, help="candidate stride (default 2)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 192])
    parser.add_argument(
        "--data", default=os.environ.get("MEDSEG_DATA", str(REPO.parent / "shared" / "data"))
    )
    parser.add_argument("--n-train", type=int, default=60, help="hippocampus training cases")
    parser.add_argument("--n-test", type=int, default=40, help="hippocampus test cases")
    parser.add_argument("--stand-in", action="store_true", help="axis-extreme stand-in landmarks")
    parser.add_argument(
        "--detector", default="{}", help="extra LandmarkDetector arguments as JSON (default {})"
    )
    parser.add_argument("--out", default=None, help="also write the JSON here (default: none)")
    args = parser.parse_args(argv)
    args.detector = json.loads(args.detector)
    if args.n_landmarks is None:
        args.n_landmarks = {"phantom": 30, "scaling": 40, "hippocampus": None}[args.what]
    run = {"phantom": bench_phantom, "hippocampus": bench_hippocampus, "scaling": bench_scaling}
    t0 = time.perf_counter()
    result = run[args.what](args)
    result["wall_seconds"] = time.perf_counter() - t0
    result["cpu_count"] = os.cpu_count()
    result["load_average_at_end"] = os.getloadavg()
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
