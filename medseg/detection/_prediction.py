"""From an image to landmark probabilities: the features the forests see, the cascade, maps.

A fitted detector scores feature rows in two steps: the cascade's region forest, when there
is one, drops the rows far from every landmark, and the landmark forests give each row left
its probability per landmark. A row holds the local features of :func:`compute_features`,
followed, in an auto-context detector, by the context features of its stage-1 probability
maps (:mod:`medseg.detection._context`); those are built here too, since they are themselves
a prediction, which training reuses for the stage-1 maps of its images. Also here: the checks
of a prediction's image, mask and memory, and dense probability maps.

The functions take the fitted :class:`~medseg.detection.LandmarkDetector` as their first
argument and only read it (``predict_rows`` sets its forests' thread count).
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from joblib import effective_n_jobs

from medseg.detection._context import context_features, context_names
from medseg.detection._features import compute_features, feature_names, require_image
from medseg.detection._memory import feature_map_bytes
from medseg.errors import ImageGeometryError, LabelError, ParameterError
from medseg.memory import check_memory
from medseg.threads import thread_map

__all__ = [
    "check_feature_memory",
    "check_image",
    "check_mask",
    "forest_feature_names",
    "forest_features",
    "forest_proba",
    "forest_votes",
    "predict_cascade",
    "predict_rows",
    "probability_map",
    "scored_region",
    "stride_grid",
    "with_context",
]

CONTEXT_STRIDE = 2  # stage-1 maps for the context features: every other voxel per axis
_ROWS_PER_THREAD = 500  # fewer rows a thread are scored on the calling thread


# ---------------------------------------------------------------------------------- inputs
def check_feature_memory(image: sitk.Image, shape, settings) -> None:
    """Refuse feature maps above the memory limit before allocating them."""
    check_memory(
        feature_map_bytes(shape, spacing=image.GetSpacing()[::-1], settings=settings),
        what=f"feature maps of a {'x'.join(str(n) for n in image.GetSize())} image",
        hint="crop the image around the structure, or resample it to a coarser spacing",
    )


def check_image(detector, image) -> tuple[int, int, int]:
    """The ``(Z, Y, X)`` shape of ``image``, which must have the training images' dimension."""
    require_image(image)
    if image.GetDimension() != detector.n_dims_:
        raise ImageGeometryError(
            f"`image` is {image.GetDimension()}D but the detector was trained on "
            f"{detector.n_dims_}D images; give a {detector.n_dims_}D image"
        )
    return tuple(int(s) for s in image.GetSize()[::-1])


def check_mask(image: sitk.Image, mask, shape) -> np.ndarray | None:
    """The search region ``mask`` as a ``(Z, Y, X)`` bool array (None: the whole image)."""
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


def stride_grid(shape, stride: int) -> tuple[tuple[int, ...], np.ndarray, np.ndarray]:
    """Every ``stride``-th voxel per axis of a ``(Z, Y, X)`` array, from the first.

    Returns the grid's own shape, the ``(M, 3)`` voxel indices of its points in C order and
    their flat indices into the array.
    """
    axes = [np.arange(0, n, stride) for n in shape]
    zyx = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return tuple(len(a) for a in axes), zyx, np.ravel_multi_index(zyx.T, shape)


def scored_region(shape, mask: np.ndarray | None, stride) -> np.ndarray:
    """The voxels scored: the stride grid within ``mask`` (all of a mask thinner than it)."""
    stride = int(stride)
    if stride < 1:
        raise ParameterError(f"`stride` must be a positive integer, got {stride}")
    region = np.zeros(shape, dtype=bool)
    region[::stride, ::stride, ::stride] = True
    if mask is not None:
        region &= mask
        if not region.any():  # the mask is thinner than the stride: score all its voxels
            region = mask.copy()
    return region


# -------------------------------------------------------------------------------- features
def forest_features(detector, image: sitk.Image, precomputed) -> np.ndarray:
    """Every feature of the forests: the local ones (or ``precomputed``), and the context."""
    shape = check_image(detector, image)
    if precomputed is None:
        check_feature_memory(image, shape, detector.features)
        feats = compute_features(image, detector.features)
    else:
        feats = np.asarray(precomputed)
        n_local = detector.features.n_features
        if feats.shape != shape + (n_local,):
            raise ParameterError(
                f"`precomputed` features have shape {feats.shape}; expected "
                f"{shape + (n_local,)} from compute_features(image, detector.features)"
            )
    if getattr(detector, "stage1_", None) is not None:
        feats = with_context(detector, detector.stage1_, image, feats)
    return feats


def forest_feature_names(detector) -> list[str]:
    """Names of the columns of :func:`forest_features`."""
    names = feature_names(detector.features)
    if getattr(detector, "stage1_", None) is not None:
        n_groups = int(np.max(detector.context_groups_)) + 1
        names += context_names(n_groups, detector.context_radii_mm_)
    return names


def with_context(detector, stage1, image: sitk.Image, base: np.ndarray) -> np.ndarray:
    """``base`` features with the context features of ``stage1``'s maps appended.

    ``stage1`` scores every ``CONTEXT_STRIDE``-th voxel per axis; the landmark groups and the
    shell radii are those of ``detector``, the stage-2 detector (``stage1`` is its
    ``stage1_``, or in training a stage-1 detector fitted without the image).
    """
    shape = base.shape[:3]
    flat = base.reshape(-1, base.shape[-1])
    grid_shape, _, rows = stride_grid(shape, CONTEXT_STRIDE)
    proba = predict_cascade(stage1, flat[rows])  # (M, N), 0 where the cascade says no
    coarse = proba.T.reshape((proba.shape[1],) + grid_shape)
    ctx = context_features(
        coarse,
        spacing_zyx=np.asarray(image.GetSpacing(), dtype=float)[::-1],
        stride=CONTEXT_STRIDE,
        shape=shape,
        groups=detector.context_groups_,
        radii_mm=detector.context_radii_mm_,
    )
    return np.concatenate([base, ctx], axis=-1)


# --------------------------------------------------------------------------- probabilities
def predict_rows(detector, X: np.ndarray, landmarks=None) -> np.ndarray:
    """Probabilities ``(M, len(landmarks))`` of the feature rows ``X`` (M, F)."""
    landmarks = range(detector.n_landmarks_) if landmarks is None else landmarks
    landmarks = list(landmarks)
    out = np.zeros((X.shape[0], len(landmarks)), dtype=np.float32)
    if X.shape[0] == 0:
        return out
    for forest in detector.forests_:
        forest.n_jobs = detector.n_jobs  # forest_proba's threads
    # the trees' dtype, converted once here rather than by every forest's call
    X = np.ascontiguousarray(X, dtype=np.float32)
    if detector.mode == "per_landmark":
        for col, i in enumerate(landmarks):
            forest = detector.forests_[i]
            pos = np.flatnonzero(forest.classes_ == 1)
            if pos.size:
                out[:, col] = forest_proba(forest, X)[:, pos[0]]
    else:
        forest = detector.forests_[0]
        proba = forest_proba(forest, X)
        lookup = {int(c): j for j, c in enumerate(forest.classes_)}
        for col, i in enumerate(landmarks):
            if i + 1 in lookup:
                out[:, col] = proba[:, lookup[i + 1]]
    return out


def forest_proba(forest, X: np.ndarray) -> np.ndarray:
    """``forest.predict_proba(X)``, the same to the bit on any number of threads.

    The rows are split into one block per thread (``forest.n_jobs``, each block at least
    :data:`_ROWS_PER_THREAD` rows), and every block sums its trees in the forest's order, as
    scikit-learn does on one job (``tests/test_detection.py``). Scikit-learn's own threads
    add the trees' votes in the order they finish, so its sums change in the last bit from
    one run to the next; and on small batches (every landmark's refinement neighbourhoods,
    each by its own forest) its per-call set-up (a joblib pool over the trees, its warning
    filters) costs more than the trees.
    """
    return forest_votes(forest, X) / len(forest.estimators_)


def forest_votes(forest, X: np.ndarray, trees: slice = slice(None), start=None) -> np.ndarray:
    """The sum of the class fractions the trees ``trees`` of ``forest`` give the rows ``X``,
    added in the forest's order onto ``start`` ((M, C) float64, zeros by default), in row
    blocks on ``forest.n_jobs`` threads (:func:`forest_proba`)."""
    X = np.ascontiguousarray(X, dtype=np.float32)  # the trees' dtype (no copy if it is)
    if start is None:
        start = np.zeros((X.shape[0], forest.n_classes_), dtype=np.float64)
    n_blocks = min(effective_n_jobs(forest.n_jobs), X.shape[0] // _ROWS_PER_THREAD)
    if n_blocks <= 1:
        return _tree_sum(forest, X, trees, start)
    edges = np.linspace(0, X.shape[0], n_blocks + 1).astype(int).tolist()

    def block(bounds):
        a, b = bounds
        return _tree_sum(forest, X[a:b], trees, start[a:b])

    blocks = list(zip(edges[:-1], edges[1:], strict=True))
    return np.concatenate(thread_map(block, blocks, len(blocks)))


def _tree_sum(forest, X: np.ndarray, trees: slice, start: np.ndarray) -> np.ndarray:
    """``start`` plus the class fractions the trees ``trees`` of ``forest`` give the
    float32 rows ``X``, added in order.

    Each tree's probabilities (of a single-output forest, as every forest here is) are its
    leaves' stored class fractions, looked up for the leaf every row reaches: what
    ``predict_proba`` sums, to the bit, without its per-call checks and its copy of every
    node's values (about a tenth of the trees' time on a segmentation's rows).
    """
    if X.shape[1] != forest.n_features_in_:
        raise ValueError(
            f"X has {X.shape[1]} features, but the forest expects {forest.n_features_in_}"
        )
    total = np.array(start, dtype=np.float64)
    for tree in forest.estimators_[trees]:
        nodes = tree.tree_
        total += np.take(nodes.value[:, 0, : tree.n_classes_], nodes.apply(X), axis=0)
    return total


def region_keep(detector, X: np.ndarray) -> np.ndarray:
    """Rows of ``X`` the cascade passes on to the landmark forests (bool, (M,))."""
    region = getattr(detector, "region_forest_", None)
    if region is None or X.shape[0] == 0:
        return np.ones(X.shape[0], dtype=bool)
    # the region forest sees the local features, the first columns of either stage
    region.n_jobs = detector.n_jobs
    p = forest_proba(region, X[:, : region.n_features_in_])[:, list(region.classes_).index(1)]
    keep = p >= float(detector.region_threshold)
    floor = min(X.shape[0], max(64, X.shape[0] // 100))
    if keep.sum() < floor:  # never let the cascade empty the search region
        keep = np.zeros(X.shape[0], dtype=bool)
        keep[np.argsort(-p, kind="stable")[:floor]] = True
    return keep


def predict_cascade(
    detector, X: np.ndarray, *, rejected: float = 0.0, screen: tuple[int, int] | None = None
) -> np.ndarray:
    """Landmark probabilities of the rows of ``X``; ``rejected`` where the cascade says no.

    ``screen = (trees, rows)``: each landmark forest of a per-landmark detector gives all its
    trees only to the ``rows`` rows its first ``trees`` trees rate best, and the other rows
    rank after those (:func:`screened_proba`). None scores every row with every tree.
    """
    keep = region_keep(detector, X)
    out = np.full((X.shape[0], detector.n_landmarks_), rejected, dtype=np.float32)
    if screen is None or detector.mode != "per_landmark":
        out[keep] = predict_rows(detector, X[keep])
        return out
    X = np.ascontiguousarray(X[keep], dtype=np.float32)
    for i, forest in enumerate(detector.forests_):
        forest.n_jobs = detector.n_jobs
        out[keep, i] = screened_proba(forest, X, *screen)
    return out


def screened_proba(forest, X: np.ndarray, trees: int, rows: int) -> np.ndarray:
    """Class-1 probabilities of the rows ``X``: :func:`forest_proba`'s, to the bit, for the
    ``rows`` rows the first ``trees`` trees of ``forest`` rate best (ties to the earlier
    row); for the others, the first trees' mean capped just below the lowest of those, so
    that they rank after every row screened in.

    A candidate search keeps a few peaks per landmark: where a forest's trees agree, its
    first few already find the rows that hold them, and the rest of the trees score only
    those. The rows left out still order among themselves, for a search that needs more
    distinct peaks than the screened rows hold.
    """
    hit = np.flatnonzero(forest.classes_ == 1)
    if not hit.size:
        return np.zeros(X.shape[0])
    n_first = min(int(trees), len(forest.estimators_))
    first = forest_votes(forest, X, slice(0, n_first))
    chosen = np.argsort(-first[:, hit[0]], kind="stable")[: int(rows)]
    total = forest_votes(forest, X[chosen], slice(n_first, None), start=first[chosen])
    exact = total[:, hit[0]] / len(forest.estimators_)
    cap = np.nextafter(exact.min(initial=np.inf), -np.inf)
    out = np.minimum(first[:, hit[0]] / n_first, cap)
    out[chosen] = exact
    return out


def probability_map(detector, image: sitk.Image, *, mask, stride, precomputed) -> np.ndarray:
    """:meth:`LandmarkDetector.predict_proba_map` of a fitted detector."""
    feats = forest_features(detector, image, precomputed)
    shape = feats.shape[:3]
    region = scored_region(shape, check_mask(image, mask, shape), stride)
    rows = np.flatnonzero(region.ravel())
    proba = predict_cascade(detector, feats.reshape(-1, feats.shape[-1])[rows])
    maps = np.full((detector.n_landmarks_, int(np.prod(shape))), np.nan, dtype=np.float32)
    maps[:, rows] = proba.T
    return maps.reshape((detector.n_landmarks_,) + shape)
