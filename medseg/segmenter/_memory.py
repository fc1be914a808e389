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

__all__ = ["configured_limit", "check_mrf_memory", "check_detection_memory", "check_fit_memory"]


def configured_limit(memory_limit_gb: float | None) -> int | None:
    """The limit in bytes if set on the model, else None (environment / default)."""
    return None if memory_limit_gb is None else memory_limit_bytes(memory_limit_gb)


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
