"""Training a landmark detector: samples, forests, hard negatives, the cascade, auto-context.

:func:`fit_detector` is what :meth:`LandmarkDetector.fit` runs once the parameters are
checked. Per training image (and per scaled or posed copy, ``augment_scales``,
``augment_poses``) it computes the
features and draws each landmark's positives and negatives (:mod:`._sampling`) plus a pool
of random voxels; fits the cascade's region forest on the pools, then the landmark forests;
and, per round of hard-negative mining, adds the pool voxels those forests score highest
away from each landmark as negatives and refits. An auto-context detector first fits its
stage 1 (and, cross-fitted, the stage-1 detectors that give its training images their
context features).

The functions take the detector as their first argument and set its fitted attributes. The
random draws happen in a fixed order from one ``RandomState``, so a seed gives one detector.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import SimpleITK as sitk
from joblib import Parallel, delayed
from sklearn.ensemble import ExtraTreesClassifier, RandomForestClassifier
from sklearn.utils import check_random_state
from tqdm.auto import tqdm

from medseg.detection._context import context_radii, landmark_groups
from medseg.detection._features import compute_features
from medseg.detection._prediction import (
    check_feature_memory,
    forest_feature_names,
    predict_rows,
    with_context,
)
from medseg.detection._sampling import sample_landmark_voxels
from medseg.errors import CohortError, ImageGeometryError, LandmarkFileError
from medseg.io import random_pose, voxel_to_physical
from medseg.progress import show_progress

__all__ = ["check_training_data", "fit_detector"]

_MAX_POOL_TOTAL = 400_000  # random voxels over all training images, for mining and the cascade


def check_training_data(
    images: Sequence[sitk.Image], landmarks: Sequence[np.ndarray]
) -> tuple[list, list, int]:
    """The training images and landmark arrays as lists, and the number of landmarks."""
    images = list(images)
    landmarks = [np.asarray(p, dtype=float) for p in landmarks]
    if not images:
        raise CohortError("fit: `images` is empty; give at least one training image")
    if len(images) != len(landmarks):
        raise CohortError(
            f"fit: {len(images)} images but {len(landmarks)} landmark arrays; give one "
            "(N, 3) array per image"
        )
    n_lm = landmarks[0].shape[0] if landmarks[0].ndim == 2 else -1
    for k, pts in enumerate(landmarks):
        if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] != n_lm or n_lm < 1:
            raise LandmarkFileError(
                f"fit: landmarks[{k}] has shape {pts.shape}; every image needs the same "
                f"(N, 3) array in mm (N = {n_lm} from landmarks[0])"
            )
    for k, image in enumerate(images):
        if not isinstance(image, sitk.Image) or image.GetDimension() != 3:
            dim = image.GetDimension() if isinstance(image, sitk.Image) else None
            raise ImageGeometryError(
                f"fit: images[{k}] is not a 3D SimpleITK image (dimension {dim}); "
                "landmark detection trains on 3D images"
            )
    return images, landmarks, n_lm


def fit_detector(detector, images, landmarks) -> None:
    """Fit ``detector`` (parameters already checked) on the images and their landmarks."""
    images, landmarks, n_lm = check_training_data(images, landmarks)
    rng = check_random_state(detector.random_state)
    detector.stage1_ = None
    detector.context_groups_ = None
    detector.context_radii_mm_ = None
    if detector.auto_context:
        features_of = _fit_stage1(detector, images, landmarks, rng)
    else:

        def features_of(k, image):
            return compute_features(image, detector.features)

    _fit_stage(detector, images, landmarks, n_lm, features_of, rng)


def _scaled(image: sitk.Image, pts: np.ndarray, factor: float):
    """The image and landmarks magnified by ``factor`` about the world origin (no resampling)."""
    if factor == 1.0:
        return image, pts
    out = sitk.Image(image)
    out.SetSpacing([v * factor for v in image.GetSpacing()])
    out.SetOrigin([v * factor for v in image.GetOrigin()])
    return out, pts * factor


def _posed(image: sitk.Image, pts: np.ndarray, detector, rng):
    """A copy of the image and landmarks in a random pose, scale and field of view
    (:func:`medseg.io.random_pose` about the landmarks' centroid, with the detector's
    ``augment_*`` ranges): the forests then cannot learn where the crop's edge lies
    relative to the anatomy."""
    centre = pts[np.isfinite(pts).all(axis=1)].mean(axis=0)
    moved, rotation, scale, offset = random_pose(
        image,
        centre,
        max_angle_deg=detector.augment_angle_deg,
        scale_range=detector.augment_scale_range,
        pad_mm=detector.augment_pad_mm,
        random_state=rng,
    )
    return moved, scale * pts @ rotation.T + offset


# ------------------------------------------------------------------------------ auto-context
def _fit_stage1(detector, images, landmarks, rng):
    """Fit the auto-context's first stage; return the training images' feature function.

    Stage 1 is fitted on all training images (it is what runs at prediction) and, for the
    stage-1 maps of the training images themselves, once per fold without that fold.
    """
    shapes = np.stack(landmarks)
    detector.context_groups_ = landmark_groups(
        shapes, int(detector.context_groups), random_state=rng
    )
    detector.context_radii_mm_ = context_radii(shapes)
    params = {**detector.get_params(deep=False), "auto_context": False, "verbose": False}

    def stage(idx):
        seed = int(rng.randint(np.iinfo(np.int32).max))
        stage_detector = type(detector)(**{**params, "random_state": seed})
        return stage_detector.fit([images[i] for i in idx], [landmarks[i] for i in idx])

    detector.stage1_ = stage(range(len(images)))
    n_folds = min(int(detector.context_folds), len(images))
    fold_of = np.arange(len(images)) % n_folds
    rng.shuffle(fold_of)
    if n_folds < 2:  # one training image: its own stage-1 maps are all there is
        held_out = {0: detector.stage1_}
    else:
        held_out = {}
        for f in range(n_folds):
            # its own cascade too: a region forest that saw the held-out image would
            # make its training maps cleaner than any map at test time
            fold_detector = stage(np.flatnonzero(fold_of != f))
            held_out.update({int(k): fold_detector for k in np.flatnonzero(fold_of == f)})

    def features_of(k, image):
        base = compute_features(image, detector.features)
        return with_context(detector, held_out[k], image, base)

    return features_of


# ----------------------------------------------------------------------------------- one stage
def _fit_stage(detector, images, landmarks, n_lm, features_of, rng) -> None:
    """Sample, fit the cascade and the forests, mine hard negatives, refit."""
    X_pos = [[] for _ in range(n_lm)]
    X_neg = [[] for _ in range(n_lm)]
    pools = []  # (features, positions mm) of random voxels per image, for mining
    use_region = detector.region_radius_mm is not None
    n_rounds = int(detector.n_mining_rounds)
    n_pool = int(detector.n_mining_pool) if (n_rounds > 0 or use_region) else 0
    copies = [("scale", 1.0)] + [("scale", float(v)) for v in detector.augment_scales]
    copies += [("pose", None)] * int(detector.augment_poses)
    # Every pool voxel is scored by every landmark's forest when mining: with many images
    # (hippocampus, 48 cases x 20000 voxels x 66 forests) that dominated the training.
    n_pool = min(n_pool, _MAX_POOL_TOTAL // max(1, len(images) * len(copies)))
    progress = detector.verbose and show_progress()
    jobs = [
        (k, image, pts, copy)
        for k, (image, pts) in enumerate(zip(images, landmarks, strict=True))
        for copy in copies
    ]
    # one seed per copy, drawn up front: the copies run in any order, on any thread count,
    # and give the same samples
    copy_seeds = rng.randint(np.iinfo(np.int32).max, size=len(jobs))
    run = Parallel(n_jobs=detector.n_jobs, prefer="threads", return_as="generator")
    samples = run(
        delayed(_copy_samples)(detector, features_of, *job, n_pool, int(seed))
        for job, seed in zip(jobs, copy_seeds, strict=True)
    )
    for pos, neg, pool in tqdm(samples, total=len(jobs), desc="features", disable=not progress):
        for i in range(n_lm):
            X_pos[i].append(pos[i])
            X_neg[i].append(neg[i])
        if pool is not None:
            pools.append(pool)
    X_pos = [np.concatenate(x) for x in X_pos]
    X_neg = [np.concatenate(x) for x in X_neg]
    missing = [i for i in range(n_lm) if X_pos[i].shape[0] == 0]
    if missing:
        raise CohortError(
            f"fit: landmark(s) {missing} are missing or outside the image in every training "
            "image; drop them or fix the landmark files"
        )
    seeds = rng.randint(np.iinfo(np.int32).max, size=n_lm + 2)
    detector.region_forest_ = (
        _fit_region(detector, pools, X_pos, int(seeds[-2])) if use_region else None
    )
    # mining scores the pools with the forests fitted so far
    detector.forests_ = _fit_forests(detector, X_pos, X_neg, seeds, progress)
    detector.n_landmarks_ = int(n_lm)
    for _ in range(n_rounds):
        mined = _mine(detector, pools)
        X_neg = [np.concatenate([x, m]) for x, m in zip(X_neg, mined, strict=True)]
        detector.forests_ = _fit_forests(detector, X_pos, X_neg, seeds, progress)
    detector.n_samples_ = np.array(
        [[len(n), len(p)] for n, p in zip(X_neg, X_pos, strict=True)], dtype=int
    )
    detector.feature_names_ = forest_feature_names(detector)
    detector.n_features_ = len(detector.feature_names_)
    detector.n_dims_ = 3


def _copy_samples(detector, features_of, k, image, pts, copy, n_pool: int, seed: int):
    """One training copy's positive and negative rows per landmark, and its mining pool.

    The copy is the image scaled or posed (``copy``), its features computed and its voxels
    sampled with a generator of its own (``seed``), so that copies can run in parallel.
    """
    rng = np.random.RandomState(seed)
    kind, factor = copy
    if kind == "scale":
        image, pts = _scaled(image, pts, factor)
    else:
        image, pts = _posed(image, pts, detector, rng)
    check_feature_memory(image, image.GetSize()[::-1], detector.features)
    feats = features_of(k, image)
    flat = feats.reshape(-1, feats.shape[-1])
    samples = sample_landmark_voxels(
        image,
        pts,
        positive_radius_mm=float(detector.positive_radius_mm),
        n_negative=int(detector.n_negative),
        max_positive=int(detector.max_positive),
        random_state=rng,
    )
    pos = [flat[p] for p in samples.positives]
    neg = [flat[q] for q in samples.negatives]
    pool = None
    if n_pool:
        idx = rng.choice(flat.shape[0], min(n_pool, flat.shape[0]), replace=False)
        zyx = np.stack(np.unravel_index(idx, feats.shape[:3]), axis=-1)
        pool = (flat[idx], voxel_to_physical(image, zyx), pts)
    return pos, neg, pool


# ---------------------------------------------------------------------------------- forests
def _bootstrap_size(detector, n_rows: int) -> int | None:
    """Rows per tree: scikit-learn's ``max_samples`` (None: as many as there are)."""
    if detector.max_tree_samples is None or n_rows <= int(detector.max_tree_samples):
        return None
    return int(detector.max_tree_samples)


def _forest(detector, seed: int, *, n_rows: int):
    """An unfitted landmark forest with the detector's settings."""
    if detector.forest == "extra_trees":
        extra = {}
        cls = ExtraTreesClassifier
    else:
        extra = {"max_samples": _bootstrap_size(detector, n_rows)}
        cls = RandomForestClassifier
    return cls(
        n_estimators=int(detector.n_estimators),
        max_depth=detector.max_depth,
        min_samples_leaf=int(detector.min_samples_leaf),
        max_features=detector.max_features,
        class_weight="balanced",
        n_jobs=detector.n_jobs,
        random_state=seed,
        **extra,
    )


def _fit_forests(detector, X_pos, X_neg, seeds, progress) -> list:
    """The landmark forests: one binary forest per landmark, or one multi-class forest."""
    n_lm = len(X_pos)
    if detector.mode == "per_landmark":
        forests = []
        for i in tqdm(range(n_lm), desc="forests", disable=not progress):
            X = np.concatenate([X_neg[i], X_pos[i]])
            y = np.r_[np.zeros(len(X_neg[i]), int), np.ones(len(X_pos[i]), int)]
            forests.append(_forest(detector, int(seeds[i]), n_rows=len(y)).fit(X, y))
        return forests
    X = np.concatenate(X_neg + X_pos)
    y = np.concatenate(
        [np.zeros(sum(len(x) for x in X_neg), int)]
        + [np.full(len(X_pos[i]), i + 1, int) for i in range(n_lm)]
    )
    return [_forest(detector, int(seeds[-1]), n_rows=len(y)).fit(X, y)]


def _fit_region(detector, pools, X_pos, seed: int):
    """Cascade stage: a forest telling voxels near any landmark from the rest.

    Trained on the random voxel pools (label 1 within ``region_radius_mm`` of a landmark)
    plus every landmark's positives. At prediction it discards most of the search region
    before the landmark forests run, which saves their time and removes far-away false
    positives (background structures that look like a boundary).
    """
    radius = float(detector.region_radius_mm)
    X, y = [], []
    for X_pool, pos_mm, pts in pools:
        ok = np.isfinite(pts).all(axis=1)
        d = np.linalg.norm(pos_mm[:, None, :] - pts[ok][None], axis=-1).min(axis=1)
        X.append(X_pool)
        y.append((d <= radius).astype(int))
    X = np.concatenate(X + list(X_pos))
    y = np.concatenate(y + [np.ones(len(x), int) for x in X_pos])
    forest = RandomForestClassifier(
        n_estimators=16,
        max_depth=12,
        min_samples_leaf=int(detector.min_samples_leaf),
        class_weight="balanced",
        max_samples=_bootstrap_size(detector, len(y)),
        n_jobs=detector.n_jobs,
        random_state=seed,
    )
    return forest.fit(X, y)


def _mine(detector, pools) -> list[np.ndarray]:
    """Hard negatives: the best-scoring pool voxels away from each landmark (bootstrapping).

    For every training image and landmark, the ``n_negative // 2`` pool voxels with the
    highest probability among those farther than ``2 * positive_radius_mm`` from the
    landmark become extra negatives.
    """
    n_lm = detector.n_landmarks_
    n_hard = max(1, int(detector.n_negative) // 2)
    exclusion = 2.0 * float(detector.positive_radius_mm)
    mined = [[] for _ in range(n_lm)]
    for X_pool, pos_mm, pts in pools:
        proba = predict_rows(detector, X_pool)
        for i in range(n_lm):
            if not np.isfinite(pts[i]).all():
                continue
            far = np.linalg.norm(pos_mm - pts[i], axis=1) > exclusion
            cand = np.flatnonzero(far)
            top = cand[np.argsort(-proba[cand, i], kind="stable")[:n_hard]]
            mined[i].append(X_pool[top])
    width = pools[0][0].shape[1] if pools else detector.n_features_
    return [np.concatenate(m) if m else np.empty((0, width), np.float32) for m in mined]
