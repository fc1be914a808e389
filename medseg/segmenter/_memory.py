"""The segmenter's memory guards: each large allocation is estimated and checked first.

A refused computation raises :class:`~medseg.errors.ResourceLimitError` before it starts,
with the estimate, the limit, and what to lower (the estimates are :mod:`medseg.memory`'s
and :func:`medseg.detection.feature_map_bytes`).
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

from medseg.detection import FeatureSettings, LandmarkDetector, detection_bytes, feature_map_bytes
from medseg.geometry import procrustes_mean
from medseg.memory import check_memory, format_bytes, memory_limit_bytes, triplet_mrf_bytes
from medseg.shape import select_cliques

__all__ = [
    "configured_limit",
    "segment_bytes",
    "check_mrf_memory",
    "check_detection_memory",
    "check_fit_memory",
]


def configured_limit(memory_limit_gb: float | None) -> int | None:
    """The limit in bytes if set on the model, else None (environment / default)."""
    return None if memory_limit_gb is None else memory_limit_bytes(memory_limit_gb)


def segment_bytes(model, size, spacing, *, use_prior: bool = True) -> int:
    """Estimated peak memory (bytes) of ``model.segment`` on an image of ``size``.

    The larger of the two allocations the guards below check: landmark detection
    (:func:`~medseg.detection.detection_bytes`) and, with the prior, the shape-prior MRF
    (:func:`~medseg.memory.triplet_mrf_bytes`); ``tests/test_resources.py`` compares it
    with the measured peak. What ``medseg-segment --jobs`` sizes its worker processes by.

    Parameters
    ----------
    model : ShapePriorSegmenter
        A fitted model.
    size, spacing : sequence of 3
        The image's size (voxels) and spacing (mm) in SimpleITK's (x, y, z) order.
    use_prior : bool
        False for detection only (``segment(..., use_prior=False)``): no MRF.
    """
    detector = model.detector_
    peak = detection_bytes(
        tuple(size)[::-1],
        spacing=tuple(spacing)[::-1],
        settings=detector.features,
        n_landmarks=detector.n_landmarks_,
    )
    if use_prior:
        mrf = triplet_mrf_bytes(
            detector.n_landmarks_,
            len(model.prior_.cliques_),
            int(model.n_candidates),
            method=model.mrf_method,
            orientation=model._uses_orientation(),
        )
        peak = max(peak, mrf)
    return int(peak)


def _mrf_hint(n_landmarks: int, n_cliques: int, n_lab: int, *, method, orientation, limit) -> str:
    fit_l = next(
        (lab for lab in range(n_lab - 1, 0, -1)
         if triplet_mrf_bytes(n_landmarks, n_cliques, lab, method=method,
                              orientation=orientation) <= limit),
        0,
    )  # fmt: skip
    lower_l = (
        f"fewer candidates per landmark (n_candidates={fit_l} fits, now {n_lab}; set "
        "model.n_candidates, no retraining needed)"
        if fit_l
        else "fewer candidates per landmark"
    )
    srmp = (
        ", or mrf_method='mplp' (SRMP keeps 4 more copies of the tables)"
        if method == "srmp"
        else ""
    )
    return (
        f"{lower_l}, or fewer cliques (retrain with cliques='delaunay' or 'knn' and fewer "
        f"landmarks){srmp}"
    )


def check_mrf_memory(
    n_landmarks: int,
    n_cliques: int,
    n_lab: int,
    *,
    method: str,
    orientation: bool,
    limit: int | None,
) -> None:
    """The potential tables and the solver's working memory of one image's MRF."""
    check_memory(
        triplet_mrf_bytes(n_landmarks, n_cliques, n_lab, method=method, orientation=orientation),
        what=(
            f"the shape-prior MRF ({n_cliques} triplet cliques x {n_lab}^3 candidate "
            f"triples: {format_bytes(4 * n_cliques * n_lab**3)} of potential tables, "
            f"plus the {method} solver's working memory)"
        ),
        hint=_mrf_hint(
            n_landmarks,
            n_cliques,
            n_lab,
            method=method,
            orientation=orientation,
            limit=memory_limit_bytes() if limit is None else limit,
        ),
        limit=limit,
    )


def check_detection_memory(
    image: sitk.Image, detector: LandmarkDetector, limit: int | None
) -> None:
    """The feature maps and probability maps of detecting the landmarks in ``image``."""
    settings = detector.features
    check_memory(
        detection_bytes(
            image.GetSize()[::-1],
            spacing=image.GetSpacing()[::-1],
            settings=settings,
            n_landmarks=detector.n_landmarks_,
        ),
        what=(
            f"landmark detection on a {'x'.join(map(str, image.GetSize()))} image "
            f"({settings.n_features} float32 feature maps and the filters' working set)"
        ),
        hint=(
            "crop the image to the region of the structure, or resample it to a coarser "
            "spacing (the feature maps grow with the number of voxels)"
        ),
        limit=limit,
    )


def check_fit_memory(
    images: list,
    landmarks: np.ndarray,
    *,
    cliques,
    n_candidates: int,
    method: str,
    orientation: bool,
    limit: int | None,
) -> None:
    """Before training: the largest image's feature maps and the inference MRF."""
    largest = max(images, key=lambda im: int(np.prod(im.GetSize())))
    check_memory(
        feature_map_bytes(
            largest.GetSize()[::-1], spacing=largest.GetSpacing()[::-1],
            settings=FeatureSettings(),
        ),
        what=(
            f"training feature maps of the largest image "
            f"({'x'.join(map(str, largest.GetSize()))} voxels)"
        ),
        hint="crop the training images around the structure, or resample them coarser",
        limit=limit,
    )  # fmt: skip
    if isinstance(cliques, str):
        n_cliques = len(select_cliques(procrustes_mean(landmarks), method=cliques))
        check_mrf_memory(
            landmarks.shape[1],
            n_cliques,
            int(n_candidates),
            method=method,
            orientation=orientation,
            limit=limit,
        )
