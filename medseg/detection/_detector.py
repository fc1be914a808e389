"""Random-Forest landmark detectors: one forest per landmark (or one multi-class forest)."""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import SimpleITK as sitk
from sklearn.ensemble import ExtraTreesClassifier, RandomForestClassifier
from sklearn.utils import check_random_state
from tqdm.auto import tqdm

from medseg.detection._candidates import CandidateSet, non_maximum_suppression, subvoxel_peak
from medseg.detection._context import (
    context_features,
    context_names,
    context_radii,
    landmark_groups,
)
from medseg.detection._features import FeatureSettings, compute_features, feature_names
from medseg.detection._memory import feature_map_bytes
from medseg.detection._sampling import sample_landmark_voxels
from medseg.errors import (
    CohortError,
    ImageGeometryError,
    LabelError,
    LandmarkFileError,
    MedsegError,
    NotFittedError,
)
from medseg.io import voxel_to_physical
from medseg.memory import check_memory
from medseg.progress import show_progress

__all__ = ["LandmarkDetector"]

_MODES = ("per_landmark", "multiclass")
_DEFAULT_FEATURES = FeatureSettings()  # frozen, so sharing it as a default is safe
_MAX_POOL_TOTAL = 400_000  # random voxels over all training images, for mining and the cascade
_CONTEXT_STRIDE = 2  # stage-1 maps for the context features: every other voxel per axis


def _scaled(image: sitk.Image, pts: np.ndarray, factor: float):
    """The image and landmarks magnified by ``factor`` about the world origin (no resampling)."""
    if factor == 1.0:
        return image, pts
    out = sitk.Image(image)
    out.SetSpacing([v * factor for v in image.GetSpacing()])
    out.SetOrigin([v * factor for v in image.GetOrigin()])
    return out, pts * factor


class LandmarkDetector:
    """Per-voxel landmark detector: Random Forests on pose-invariant features.

    The singleton evidence of the shape MRF, ``U_i(x_i) = -log p(I | x_i)``, and the candidate
    sets ``X_i`` (Wang et al., MICCAI 2010). ``__init__`` only stores its arguments.

    Parameters
    ----------
    features : FeatureSettings
        Which features to compute; stored with the model, so a loaded detector computes the
        same features.
    positive_radius_mm : float, mm
        Voxels within this distance of a landmark are its positive samples.
    n_estimators, max_depth, min_samples_leaf, max_features
        Passed to each :class:`sklearn.ensemble.RandomForestClassifier`.
    max_tree_samples : int or None
        Each tree of a random forest is grown on a bootstrap sample of at most this many
        rows (scikit-learn's ``max_samples``), so training time stops growing with the
        number of training images once the samples of a landmark exceed it (about 36
        images at the default). None: bootstrap samples as large as the training set.
        Ignored by ``forest="extra_trees"``, which does not bootstrap.
    mode : {"per_landmark", "multiclass"}
        One binary forest per landmark, as in the paper, or a single forest with a class per
        landmark plus background.
    n_negative : int
        Negative samples per landmark and training image (ring around the landmark, near the
        other landmarks, and uniform; see :func:`sample_landmark_voxels`).
    max_positive : int
        At most this many positive samples per landmark and training image.
    n_mining_rounds : int
        Rounds of hard-negative mining (bootstrapping): after fitting, the best-scoring
        voxels away from each landmark in a random pool of every training image are added as
        negatives and the forests refitted. 0 disables it.
    n_mining_pool : int
        Random voxels per training image scored in each mining round (and training the
        cascade); at most 400 000 over all training images.
    augment_scales : tuple of float
        Extra copies of every training image, scaled about the world origin by these factors
        (only the spacing and origin change, so no resampling): the forests see the anatomy
        at other sizes, as a new subject may be bigger or smaller.
    region_radius_mm : float or None, mm
        Cascade: a first forest learns where *any* landmark is within this distance, and
        only the voxels it accepts are scored by the landmark forests (faster, fewer far-away
        false positives). None disables it.
    region_threshold : float
        Probability above which the cascade accepts a voxel (at least 1 % of the search
        region is always kept).
    forest : {"random_forest", "extra_trees"}
        Random Forests (as in the paper) or extremely randomised trees.
    auto_context : bool
        Two stages (see :mod:`medseg.detection._context`): stage-1 forests on the local
        features, then the final forests on the local features plus spherical-shell means of
        the stage-1 probability of ``context_groups`` groups of landmarks. The stage-1 maps
        of the training images come from forests fitted without them (``context_folds``-fold
        cross-fitting). About three times the training time and twice the prediction time
        of one stage. Off by default: its gain is not established (see the module notes).
    context_groups : int
        Landmarks are grouped by position (k-means on the mean training shape) into this
        many context channels per radius.
    context_folds : int
        Folds of the cross-fitting of the stage-1 maps of the training images.
    random_state : int, RandomState or None
        Seeds the sampling and the forests; the same seed gives the same detector.
    n_jobs : int
        Threads used by the forests (fit and predict).
    verbose : bool
        Show tqdm progress on a terminal.

    Attributes
    ----------
    forests_ : list of RandomForestClassifier
        ``n_landmarks_`` binary forests (``mode="per_landmark"``) or one forest.
    n_landmarks_ : int
    n_features_ : int
    feature_names_ : list of str
    region_forest_ : RandomForestClassifier or None
        The cascade's first stage.
    stage1_ : LandmarkDetector or None
        The auto-context's first stage (``auto_context=True``).
    context_groups_ : (n_landmarks_,) int array or None
    context_radii_mm_ : tuple of float or None
        Shell radii of the context features, from the training landmarks' distances.
    n_dims_ : int
        Dimension of the training images (3).
    n_samples_ : (n_landmarks_, 2) int array
        Negative and positive training samples of each landmark.
    fit_time_ : float, s
    """

    def __init__(
        self,
        *,
        features: FeatureSettings = _DEFAULT_FEATURES,
        positive_radius_mm: float = 2.0,
        n_estimators: int = 32,
        max_depth: int | None = 14,
        min_samples_leaf: int = 2,
        max_features: str | int | float = "sqrt",
        max_tree_samples: int | None = 20000,
        mode: str = "per_landmark",
        n_negative: int = 300,
        max_positive: int = 100,
        n_mining_rounds: int = 1,
        n_mining_pool: int = 20000,
        augment_scales: tuple[float, ...] = (),
        region_radius_mm: float | None = 6.0,
        region_threshold: float = 0.2,
        forest: str = "random_forest",
        auto_context: bool = False,
        context_groups: int = 8,
        context_folds: int = 2,
        random_state=None,
        n_jobs: int = 1,
        verbose: bool = False,
    ):
        self.features = features
        self.positive_radius_mm = positive_radius_mm
        self.n_estimators = n_estimators
        self.max_depth = max_depth
        self.min_samples_leaf = min_samples_leaf
        self.max_features = max_features
        self.max_tree_samples = max_tree_samples
        self.mode = mode
        self.n_negative = n_negative
        self.max_positive = max_positive
        self.n_mining_rounds = n_mining_rounds
        self.n_mining_pool = n_mining_pool
        self.augment_scales = augment_scales
        self.region_radius_mm = region_radius_mm
        self.region_threshold = region_threshold
        self.forest = forest
        self.auto_context = auto_context
        self.context_groups = context_groups
        self.context_folds = context_folds
        self.random_state = random_state
        self.n_jobs = n_jobs
        self.verbose = verbose

    # ------------------------------------------------------------------ parameters
    def get_params(self, deep: bool = False) -> dict:
        """Constructor arguments, as in scikit-learn."""
        names = (
            "features positive_radius_mm n_estimators max_depth min_samples_leaf max_features "
            "max_tree_samples mode n_negative max_positive n_mining_rounds n_mining_pool "
            "augment_scales region_radius_mm region_threshold "
            "forest auto_context context_groups context_folds random_state n_jobs verbose"
        ).split()
        return {n: getattr(self, n) for n in names}

    def set_params(self, **params) -> LandmarkDetector:
        valid = self.get_params()
        for key, value in params.items():
            if key not in valid:
                raise MedsegError(f"LandmarkDetector has no parameter {key!r}; see get_params()")
            setattr(self, key, value)
        return self

    def __repr__(self) -> str:
        return f"LandmarkDetector(mode={self.mode!r}, n_estimators={self.n_estimators})"

    def _validate_params(self) -> None:
        if not isinstance(self.features, FeatureSettings):
            raise MedsegError(
                f"`features` must be a FeatureSettings, got {type(self.features).__name__}"
            )
        if self.forest not in ("random_forest", "extra_trees"):
            raise MedsegError(
                f"`forest` must be 'random_forest' or 'extra_trees', got {self.forest!r}"
            )
        if self.mode not in _MODES:
            raise MedsegError(f"`mode` must be one of {_MODES}, got {self.mode!r}")
        if not float(self.positive_radius_mm) > 0:
            raise MedsegError(f"`positive_radius_mm` must be > 0, got {self.positive_radius_mm}")
        for name in (
            "n_estimators",
            "n_negative",
            "max_positive",
            "min_samples_leaf",
            "context_groups",
        ):
            if int(getattr(self, name)) < 1:
                raise MedsegError(f"`{name}` must be a positive integer, got {getattr(self, name)}")
        if self.max_tree_samples is not None and int(self.max_tree_samples) < 1:
            raise MedsegError(
                f"`max_tree_samples` must be a positive integer or None, got "
                f"{self.max_tree_samples}"
            )
        if int(self.context_folds) < 2:
            raise MedsegError(f"`context_folds` must be at least 2, got {self.context_folds}")

    def _forest(self, seed: int, *, n_rows: int):
        if self.forest == "extra_trees":
            extra = {}
            cls = ExtraTreesClassifier
        else:
            extra = {"max_samples": self._bootstrap_size(n_rows)}
            cls = RandomForestClassifier
        return cls(
            n_estimators=int(self.n_estimators),
            max_depth=self.max_depth,
            min_samples_leaf=int(self.min_samples_leaf),
            max_features=self.max_features,
            class_weight="balanced",
            n_jobs=self.n_jobs,
            random_state=seed,
            **extra,
        )

    def _bootstrap_size(self, n_rows: int) -> int | None:
        """Rows per tree: scikit-learn's ``max_samples`` (None: as many as there are)."""
        if self.max_tree_samples is None or n_rows <= int(self.max_tree_samples):
            return None
        return int(self.max_tree_samples)

    # ------------------------------------------------------------------ fit
    def fit(
        self,
        images: Sequence[sitk.Image],
        landmarks: Sequence[np.ndarray],
    ) -> LandmarkDetector:
        """Train the forests.

        Parameters
        ----------
        images : list of 3D SimpleITK images
            Training images; any spacing and direction.
        landmarks : list of (N, 3) float arrays, mm, (x, y, z)
            The landmarks of each image, in correspondence (row ``i`` is the same anatomical
            point in every image). Rows with NaN are missing and ignored.

        Returns
        -------
        self
        """
        return self._fit(images, landmarks)

    def _fit(self, images, landmarks, *, region_forest=None) -> LandmarkDetector:
        """:meth:`fit`, optionally with the cascade's region forest given (not refitted)."""
        t0 = time.perf_counter()
        self._validate_params()
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
        rng = check_random_state(self.random_state)
        self.stage1_ = None
        self.context_groups_ = None
        self.context_radii_mm_ = None
        if self.auto_context:
            features_of = self._fit_stage1(images, landmarks, rng)
        else:

            def features_of(k, image):
                return compute_features(image, self.features)

        self._fit_stage(images, landmarks, n_lm, features_of, rng, region_forest)
        self.fit_time_ = time.perf_counter() - t0
        return self

    def _fit_stage1(self, images, landmarks, rng):
        """Fit the auto-context's first stage; return the training images' feature function.

        Stage 1 is fitted on all training images (it is what runs at prediction) and, for the
        stage-1 maps of the training images themselves, once per fold without that fold.
        """
        shapes = np.stack(landmarks)
        self.context_groups_ = landmark_groups(shapes, int(self.context_groups), random_state=rng)
        self.context_radii_mm_ = context_radii(shapes)
        params = {**self.get_params(), "auto_context": False, "verbose": False}

        def stage(idx, region_forest=None):
            seed = int(rng.randint(np.iinfo(np.int32).max))
            det = LandmarkDetector(**{**params, "random_state": seed})
            return det._fit(
                [images[i] for i in idx],
                [landmarks[i] for i in idx],
                region_forest=region_forest,
            )

        self.stage1_ = stage(range(len(images)))
        n_folds = min(int(self.context_folds), len(images))
        fold_of = np.arange(len(images)) % n_folds
        rng.shuffle(fold_of)
        if n_folds < 2:  # one training image: its own stage-1 maps are all there is
            held_out = {0: self.stage1_}
        else:
            held_out = {}
            for f in range(n_folds):
                # its own cascade too: a region forest that saw the held-out image would
                # make its training maps cleaner than any map at test time
                det = stage(np.flatnonzero(fold_of != f))
                held_out.update({int(k): det for k in np.flatnonzero(fold_of == f)})

        def features_of(k, image):
            base = compute_features(image, self.features)
            return self._with_context(held_out[k], image, base)

        return features_of

    def _with_context(self, stage1, image, base: np.ndarray) -> np.ndarray:
        """``base`` features with the context features of ``stage1``'s maps appended."""
        shape = base.shape[:3]
        flat = base.reshape(-1, base.shape[-1])
        s = _CONTEXT_STRIDE
        gz, gy, gx = (np.arange(0, n, s) for n in shape)
        grid = np.stack(np.meshgrid(gz, gy, gx, indexing="ij"), -1).reshape(-1, 3)
        rows = np.ravel_multi_index(grid.T, shape)
        proba = stage1._predict_cascade(flat[rows])  # (M, N), 0 where the cascade says no
        coarse = proba.T.reshape((proba.shape[1], len(gz), len(gy), len(gx)))
        ctx = context_features(
            coarse,
            spacing_zyx=np.asarray(image.GetSpacing(), dtype=float)[::-1],
            stride=s,
            shape=shape,
            groups=self.context_groups_,
            radii_mm=self.context_radii_mm_,
        )
        return np.concatenate([base, ctx], axis=-1)

    def _fit_stage(self, images, landmarks, n_lm, features_of, rng, region_forest) -> None:
        """Sample, fit the forests (and the cascade unless given), mine hard negatives, refit."""
        X_pos = [[] for _ in range(n_lm)]
        X_neg = [[] for _ in range(n_lm)]
        pools = []  # (features, positions mm) of random voxels per image, for mining
        use_region = self.region_radius_mm is not None
        n_pool = int(self.n_mining_pool) if (int(self.n_mining_rounds) > 0 or use_region) else 0
        scales = (1.0,) + tuple(float(v) for v in self.augment_scales)
        # Every pool voxel is scored by every landmark's forest when mining: with many images
        # (hippocampus, 48 cases x 20000 voxels x 66 forests) that dominated the training.
        n_pool = min(n_pool, _MAX_POOL_TOTAL // max(1, len(images) * len(scales)))
        progress = self.verbose and show_progress()
        jobs = [
            (k, image, pts, s)
            for k, (image, pts) in enumerate(zip(images, landmarks, strict=True))
            for s in scales
        ]
        for k, image, pts, factor in tqdm(jobs, desc="features", disable=not progress):
            image, pts = _scaled(image, pts, factor)
            self._check_feature_memory(image, image.GetSize()[::-1])
            feats = features_of(k, image)
            flat = feats.reshape(-1, feats.shape[-1])
            samples = sample_landmark_voxels(
                image,
                pts,
                positive_radius_mm=float(self.positive_radius_mm),
                n_negative=int(self.n_negative),
                max_positive=int(self.max_positive),
                random_state=rng,
            )
            for i in range(n_lm):
                X_pos[i].append(flat[samples.positives[i]])
                X_neg[i].append(flat[samples.negatives[i]])
            if n_pool:
                idx = rng.choice(flat.shape[0], min(n_pool, flat.shape[0]), replace=False)
                zyx = np.stack(np.unravel_index(idx, feats.shape[:3]), axis=-1)
                pools.append((flat[idx].copy(), voxel_to_physical(image, zyx), pts))
            del feats, flat
        X_pos = [np.concatenate(x) for x in X_pos]
        X_neg = [np.concatenate(x) for x in X_neg]
        missing = [i for i in range(n_lm) if X_pos[i].shape[0] == 0]
        if missing:
            raise CohortError(
                f"fit: landmark(s) {missing} are missing or outside the image in every training "
                "image; drop them or fix the landmark files"
            )
        seeds = rng.randint(np.iinfo(np.int32).max, size=n_lm + 2)
        if region_forest is None and use_region:
            region_forest = self._fit_region(pools, X_pos, int(seeds[-2]))
        self.region_forest_ = region_forest if use_region else None
        forests = self._fit_forests(X_pos, X_neg, seeds, progress)
        self.forests_ = forests
        self.n_landmarks_ = int(n_lm)
        for _ in range(int(self.n_mining_rounds)):
            mined = self._mine(pools)
            X_neg = [np.concatenate([x, m]) for x, m in zip(X_neg, mined, strict=True)]
            forests = self._fit_forests(X_pos, X_neg, seeds, progress)
            self.forests_ = forests
        self.n_samples_ = np.array(
            [[len(n), len(p)] for n, p in zip(X_neg, X_pos, strict=True)], dtype=int
        )
        self.forests_ = forests
        self.n_landmarks_ = int(n_lm)
        self.feature_names_ = self._feature_names()
        self.n_features_ = len(self.feature_names_)
        self.n_dims_ = 3

    def _feature_names(self) -> list[str]:
        names = feature_names(self.features)
        if getattr(self, "stage1_", None) is not None:
            n_groups = int(np.max(self.context_groups_)) + 1
            names += context_names(n_groups, self.context_radii_mm_)
        return names

    def _fit_region(self, pools, X_pos, seed: int):
        """Cascade stage: a forest telling voxels near any landmark from the rest.

        Trained on the random voxel pools (label 1 within ``region_radius_mm`` of a landmark)
        plus every landmark's positives. At prediction it discards most of the search region
        before the landmark forests run, which saves their time and removes far-away false
        positives (background structures that look like a boundary).
        """
        radius = float(self.region_radius_mm)
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
            min_samples_leaf=int(self.min_samples_leaf),
            class_weight="balanced",
            max_samples=self._bootstrap_size(len(y)),
            n_jobs=self.n_jobs,
            random_state=seed,
        )
        return forest.fit(X, y)

    def _region_keep(self, X: np.ndarray) -> np.ndarray:
        """Rows of ``X`` the cascade passes on to the landmark forests (bool, (M,))."""
        region = getattr(self, "region_forest_", None)
        if region is None or X.shape[0] == 0:
            return np.ones(X.shape[0], dtype=bool)
        # the region forest sees the local features, the first columns of either stage
        p = region.predict_proba(X[:, : region.n_features_in_])[:, list(region.classes_).index(1)]
        keep = p >= float(self.region_threshold)
        floor = min(X.shape[0], max(64, X.shape[0] // 100))
        if keep.sum() < floor:  # never let the cascade empty the search region
            keep = np.zeros(X.shape[0], dtype=bool)
            keep[np.argsort(-p, kind="stable")[:floor]] = True
        return keep

    def _predict_cascade(self, X: np.ndarray, *, rejected: float = 0.0) -> np.ndarray:
        """Landmark probabilities of the rows of ``X``; ``rejected`` where the cascade says no."""
        keep = self._region_keep(X)
        out = np.full((X.shape[0], self.n_landmarks_), rejected, dtype=np.float32)
        out[keep] = self._predict_rows(X[keep])
        return out

    def _fit_forests(self, X_pos, X_neg, seeds, progress) -> list:
        n_lm = len(X_pos)
        if self.mode == "per_landmark":
            forests = []
            for i in tqdm(range(n_lm), desc="forests", disable=not progress):
                X = np.concatenate([X_neg[i], X_pos[i]])
                y = np.r_[np.zeros(len(X_neg[i]), int), np.ones(len(X_pos[i]), int)]
                forests.append(self._forest(int(seeds[i]), n_rows=len(y)).fit(X, y))
            return forests
        X = np.concatenate(X_neg + X_pos)
        y = np.concatenate(
            [np.zeros(sum(len(x) for x in X_neg), int)]
            + [np.full(len(X_pos[i]), i + 1, int) for i in range(n_lm)]
        )
        return [self._forest(int(seeds[-1]), n_rows=len(y)).fit(X, y)]

    def _mine(self, pools) -> list[np.ndarray]:
        """Hard negatives: the best-scoring pool voxels away from each landmark (bootstrapping).

        For every training image and landmark, the ``n_negative // 2`` pool voxels with the
        highest probability among those farther than ``2 * positive_radius_mm`` from the
        landmark become extra negatives.
        """
        n_lm = self.n_landmarks_
        n_hard = max(1, int(self.n_negative) // 2)
        exclusion = 2.0 * float(self.positive_radius_mm)
        mined = [[] for _ in range(n_lm)]
        for X_pool, pos_mm, pts in pools:
            proba = self._predict_rows(X_pool)
            for i in range(n_lm):
                if not np.isfinite(pts[i]).all():
                    continue
                far = np.linalg.norm(pos_mm - pts[i], axis=1) > exclusion
                cand = np.flatnonzero(far)
                top = cand[np.argsort(-proba[cand, i], kind="stable")[:n_hard]]
                mined[i].append(X_pool[top])
        width = pools[0][0].shape[1] if pools else self.n_features_
        return [np.concatenate(m) if m else np.empty((0, width), np.float32) for m in mined]

    # ------------------------------------------------------------------ predict
    def _check_feature_memory(self, image: sitk.Image, shape) -> None:
        """Refuse feature maps above the memory limit before allocating them."""
        check_memory(
            feature_map_bytes(shape, spacing=image.GetSpacing()[::-1], settings=self.features),
            what=f"feature maps of a {'x'.join(str(n) for n in image.GetSize())} image",
            hint="crop the image around the structure, or resample it to a coarser spacing",
        )

    def _check_fitted(self) -> None:
        if not hasattr(self, "forests_"):
            raise NotFittedError(
                "this LandmarkDetector is not fitted yet: call fit(images, landmarks) or "
                "LandmarkDetector.load(path) first"
            )

    def _check_image(self, image) -> tuple[int, int, int]:
        if not isinstance(image, sitk.Image):
            raise MedsegError(
                f"`image` must be a SimpleITK image, got {type(image).__name__}; read files "
                "with medseg.io.read_image"
            )
        if image.GetDimension() != self.n_dims_:
            raise ImageGeometryError(
                f"`image` is {image.GetDimension()}D but the detector was trained on "
                f"{self.n_dims_}D images; give a {self.n_dims_}D image"
            )
        return tuple(int(s) for s in image.GetSize()[::-1])

    def _features(self, image, precomputed) -> np.ndarray:
        """Every feature of the forests: the local ones (or ``precomputed``), and the context."""
        shape = self._check_image(image)
        if precomputed is None:
            self._check_feature_memory(image, shape)
            feats = compute_features(image, self.features)
        else:
            feats = np.asarray(precomputed)
            n_local = self.features.n_features
            if feats.shape != shape + (n_local,):
                raise MedsegError(
                    f"`precomputed` features have shape {feats.shape}; expected "
                    f"{shape + (n_local,)} from compute_features(image, detector.features)"
                )
        if getattr(self, "stage1_", None) is not None:
            feats = self._with_context(self.stage1_, image, feats)
        return feats

    def _mask(self, image: sitk.Image, mask, shape) -> np.ndarray | None:
        if mask is None:
            return None
        if isinstance(mask, sitk.Image):
            arr = sitk.GetArrayViewFromImage(mask)
            same = (
                mask.GetSize() == image.GetSize()
                and np.allclose(mask.GetSpacing(), image.GetSpacing(), atol=1e-4)
                and np.allclose(mask.GetOrigin(), image.GetOrigin(), atol=1e-3)
                and np.allclose(mask.GetDirection(), image.GetDirection(), atol=1e-4)
            )
            if not same:
                raise ImageGeometryError(
                    "`mask` does not share the image's size, spacing, origin and direction; "
                    "resample it onto the image (nearest neighbour) first"
                )
        else:
            arr = np.asarray(mask)
        if arr.shape != shape:
            raise ImageGeometryError(
                f"`mask` has shape {arr.shape}; expected the image's (Z, Y, X) shape {shape}"
            )
        arr = arr != 0
        if not arr.any():
            raise LabelError(
                "`mask` (the search region) is empty: no voxel to search; give a mask with "
                "at least one non-zero voxel, or mask=None to search the whole image"
            )
        return arr

    def _predict_rows(self, X: np.ndarray, landmarks=None) -> np.ndarray:
        """Probabilities ``(M, len(landmarks))`` of the feature rows ``X`` (M, F)."""
        landmarks = range(self.n_landmarks_) if landmarks is None else landmarks
        landmarks = list(landmarks)
        out = np.zeros((X.shape[0], len(landmarks)), dtype=np.float32)
        if X.shape[0] == 0:
            return out
        # Threads cost more than they save on small batches (refinement neighbourhoods).
        n_jobs = self.n_jobs if X.shape[0] >= 20000 else 1
        for forest in self.forests_:
            forest.n_jobs = n_jobs
        if self.mode == "per_landmark":
            for col, i in enumerate(landmarks):
                forest = self.forests_[i]
                pos = np.flatnonzero(forest.classes_ == 1)
                if pos.size:
                    out[:, col] = forest.predict_proba(X)[:, pos[0]]
        else:
            forest = self.forests_[0]
            proba = forest.predict_proba(X)
            lookup = {int(c): j for j, c in enumerate(forest.classes_)}
            for col, i in enumerate(landmarks):
                if i + 1 in lookup:
                    out[:, col] = proba[:, lookup[i + 1]]
        return out

    def predict_proba_map(
        self,
        image: sitk.Image,
        *,
        mask=None,
        stride: int = 1,
        precomputed: np.ndarray | None = None,
    ) -> np.ndarray:
        """Probability of each landmark at each scored voxel.

        Parameters
        ----------
        image : 3D SimpleITK image
        mask : (Z, Y, X) bool array or SimpleITK image on the image's grid, optional
            Search region; default the whole image.
        stride : int
            Score every ``stride``-th voxel along each axis.
        precomputed : (Z, Y, X, F) float32 array, optional
            ``compute_features(image, self.features)``, to avoid computing it again.

        Returns
        -------
        maps : (N, Z, Y, X) float32 array
            Probabilities in [0, 1]; NaN at voxels that were not scored (outside the mask or
            off the stride grid).
        """
        self._check_fitted()
        feats = self._features(image, precomputed)
        shape = feats.shape[:3]
        region = self._region(shape, self._mask(image, mask, shape), stride)
        rows = np.flatnonzero(region.ravel())
        proba = self._predict_cascade(feats.reshape(-1, feats.shape[-1])[rows])
        maps = np.full((self.n_landmarks_, int(np.prod(shape))), np.nan, dtype=np.float32)
        maps[:, rows] = proba.T
        return maps.reshape((self.n_landmarks_,) + shape)

    @staticmethod
    def _region(shape, mask, stride) -> np.ndarray:
        stride = int(stride)
        if stride < 1:
            raise MedsegError(f"`stride` must be a positive integer, got {stride}")
        region = np.zeros(shape, dtype=bool)
        region[::stride, ::stride, ::stride] = True
        if mask is not None:
            region &= mask
            if not region.any():  # the mask is thinner than the stride: score all its voxels
                region = mask.copy()
        return region

    def candidates(
        self,
        image: sitk.Image,
        *,
        n_candidates: int = 20,
        min_distance_mm: float | None = None,
        mask=None,
        stride: int = 2,
        refine: bool = True,
        floor: float = 1e-6,
        precomputed: np.ndarray | None = None,
    ) -> CandidateSet:
        """The ``n_candidates`` best, spatially distinct positions of every landmark.

        Parameters
        ----------
        image : 3D SimpleITK image
        n_candidates : int
            L, candidates per landmark.
        min_distance_mm : float, mm, optional
            Candidates of one landmark are more than this far apart (on the stride grid).
            Default: ``max(positive_radius_mm, 2 * largest spacing)``.
        mask : (Z, Y, X) bool array or SimpleITK image on the image's grid, optional
            Search region (e.g. a foreground mask); default the whole image.
        stride : int
            Score every ``stride``-th voxel per axis; with ``refine`` the candidates are then
            re-scored at full resolution in a ``(2 stride + 1)^3`` neighbourhood.
        refine : bool
            Move each candidate to the best voxel of its neighbourhood and to a sub-voxel peak
            (parabola along each axis).
        floor : float
            Probability floor, so ``-log p`` is finite.
        precomputed : (Z, Y, X, F) float32 array, optional
            ``compute_features(image, self.features)``.

        Returns
        -------
        CandidateSet
            ``positions`` (N, L, 3) mm, ``probabilities`` (N, L), best first per landmark.
        """
        self._check_fitted()
        n_candidates = int(n_candidates)
        if n_candidates < 1:
            raise MedsegError(f"`n_candidates` must be >= 1, got {n_candidates}")
        if not 0 < floor < 1:
            raise MedsegError(f"`floor` must be in (0, 1), got {floor}")
        timings = {}
        t0 = time.perf_counter()
        feats = self._features(image, precomputed)
        timings["features_s"] = time.perf_counter() - t0
        shape = feats.shape[:3]
        flat = feats.reshape(-1, feats.shape[-1])
        mask_arr = self._mask(image, mask, shape)
        spacing = np.asarray(image.GetSpacing(), dtype=float)[::-1]
        if min_distance_mm is None:
            min_distance_mm = max(float(self.positive_radius_mm), 2.0 * float(spacing.max()))
        stride = int(stride)
        region = self._region(shape, mask_arr, stride)
        coarse_on_grid = region[::stride, ::stride, ::stride]
        on_grid = coarse_on_grid.sum() == region.sum()
        t0 = time.perf_counter()
        if on_grid:
            grid_shape = coarse_on_grid.shape
            gz, gy, gx = (np.arange(0, s, stride) for s in shape)
            grid_zyx = np.stack(np.meshgrid(gz, gy, gx, indexing="ij"), -1).reshape(-1, 3)
            grid_rows = np.ravel_multi_index(grid_zyx.T, shape)
            scored = coarse_on_grid.ravel()
            footprint = float(min_distance_mm) / (spacing * stride)
        else:  # thin mask scored voxel by voxel
            grid_shape = None
            grid_zyx = np.argwhere(region)
            grid_rows = np.ravel_multi_index(grid_zyx.T, shape)
            scored = np.ones(len(grid_rows), dtype=bool)
            footprint = None
        proba = np.full((len(grid_rows), self.n_landmarks_), -np.inf, dtype=np.float64)
        proba[scored] = self._predict_cascade(flat[grid_rows[scored]], rejected=-np.inf)
        timings["predict_s"] = time.perf_counter() - t0
        points_mm = voxel_to_physical(image, grid_zyx)

        t0 = time.perf_counter()
        n_lm = self.n_landmarks_
        n_keep = min(n_candidates, int(scored.sum()))
        vox = np.zeros((n_lm, n_candidates, 3))
        prob = np.full((n_lm, n_candidates), floor)
        for i in range(n_lm):
            keep = non_maximum_suppression(
                proba[:, i],
                points_mm,
                n=n_keep,
                min_distance_mm=float(min_distance_mm),
                grid_shape=grid_shape,
                footprint_vox=footprint,
            )
            vox[i, : len(keep)] = grid_zyx[keep]
            prob[i, : len(keep)] = proba[keep, i]
            if len(keep) < n_candidates:  # fewer scored voxels than candidates: repeat the last
                vox[i, len(keep) :] = vox[i, len(keep) - 1]
                prob[i, len(keep) :] = floor
        timings["nms_s"] = time.perf_counter() - t0
        if refine:
            t0 = time.perf_counter()
            vox, prob = self._refine(flat, shape, mask_arr, vox, prob, max(stride, 1))
            timings["refine_s"] = time.perf_counter() - t0
        positions = voxel_to_physical(image, vox.reshape(-1, 3)).reshape(vox.shape)
        return CandidateSet(
            positions=positions,
            probabilities=np.clip(prob, floor, 1.0),
            voxels=vox,
            floor=float(floor),
            meta={
                "stride": stride,
                "min_distance_mm": float(min_distance_mm),
                "refine": bool(refine),
                "mode": self.mode,
                "timings": timings,
            },
        )

    def _refine(self, flat, shape, mask, vox, prob, half):
        """Best voxel and sub-voxel peak of each candidate's full-resolution neighbourhood."""
        n_lm, n_c, _ = vox.shape
        offsets = np.stack(
            np.meshgrid(*[np.arange(-half, half + 1)] * 3, indexing="ij"), -1
        ).reshape(-1, 3)
        side = 2 * half + 1
        centres = np.rint(vox).astype(int)
        cubes = centres[:, :, None, :] + offsets[None, None]  # (N, L, K, 3)
        valid = np.all((cubes >= 0) & (cubes < np.asarray(shape)), axis=-1)
        clipped = np.clip(cubes, 0, np.asarray(shape) - 1)
        if mask is not None:
            valid &= mask[tuple(np.moveaxis(clipped, -1, 0))]
        rows = np.ravel_multi_index(tuple(np.moveaxis(clipped, -1, 0)), shape)
        values = np.full(valid.shape, np.nan)
        if self.mode == "per_landmark":
            for i in range(n_lm):
                sel = valid[i]
                values[i][sel] = self._predict_rows(flat[rows[i][sel]], [i])[:, 0]
        else:  # one pass of the multi-class forest over every neighbourhood
            unique, inverse = np.unique(rows[valid], return_inverse=True)
            proba = self._predict_rows(flat[unique])
            lm_index = np.broadcast_to(np.arange(n_lm)[:, None, None], valid.shape)[valid]
            values[valid] = proba[inverse, lm_index]
        new_vox, new_prob = vox.copy(), prob.copy()
        for i in range(n_lm):
            for c in range(n_c):
                v = values[i, c]
                if np.all(np.isnan(v)):
                    continue
                best = int(np.nanargmax(v))
                centre = v.size // 2
                if np.isfinite(v[centre]) and v[best] <= v[centre]:
                    best = centre  # ties (flat maps) keep the candidate where it is
                cube = v.reshape(side, side, side)
                local = np.unravel_index(best, cube.shape)
                offset = subvoxel_peak(cube, local)
                new_vox[i, c] = cubes[i, c, best] + offset
                new_prob[i, c] = max(v[best], 0.0)
        order = np.argsort(-new_prob, axis=1, kind="stable")
        new_vox = np.take_along_axis(new_vox, order[..., None], axis=1)
        new_prob = np.take_along_axis(new_prob, order, axis=1)
        return new_vox, new_prob

    # ------------------------------------------------------------------ persistence
    def save(self, path) -> None:
        """Save to a folder (``detector.json`` + ``forests.skops``); see :func:`save_detector`."""
        from medseg.detection._persistence import save_detector

        save_detector(self, path)

    @classmethod
    def load(cls, path) -> LandmarkDetector:
        """Load a detector saved by :meth:`save`; see :func:`load_detector`."""
        from medseg.detection._persistence import load_detector

        return load_detector(path)
