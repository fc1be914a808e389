"""Reference landmarks for cohorts that have none (real data: label maps only).

The phantom carries ground-truth landmarks per case; a real cohort such as the MSD
hippocampus does not. There, per fold:

* the training landmarks come from :func:`medseg.correspondence.landmarks_from_labels` on the
  training label maps, computed **once** and attached to the training cases, so every method
  of the fold (the segmenter, the detection baseline and the ASM) trains on the same
  landmarks;
* a test case's reference landmarks are the template's landmarks carried onto its label map
  by :func:`transfer_landmarks`: a similarity (principal axes + ICP over the boundary points),
  a non-rigid coherent-point-drift warp of the template boundary onto the test boundary, and
  a final snap of each landmark onto the nearest test boundary point.

The landmark error on real data is therefore measured against a registration-derived
reference, not against expert landmarks: it is a consistency measure and is reported as such.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import SimpleITK as sitk
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from medseg._registration import (
    cpd_nonrigid,
    farthest_point_sampling,
    icp_similarity,
    principal_axes_candidates,
)
from medseg.errors import LabelError, MedsegError
from medseg.io import select_labels, voxel_to_physical

__all__ = ["boundary_points", "transfer_landmarks", "fold_landmarks"]


def boundary_points(mask: sitk.Image) -> np.ndarray:
    """Physical centres (mm) of the boundary voxels of a binary mask, ``(M, 3)``."""
    contour = sitk.LabelContour(sitk.Cast(mask > 0, sitk.sitkUInt8), fullyConnected=True)
    zyx = np.argwhere(sitk.GetArrayViewFromImage(contour) > 0)
    if not len(zyx):
        raise LabelError("the mask is empty: no boundary to put landmarks on")
    return voxel_to_physical(mask, zyx)


def transfer_landmarks(
    template_mask: sitk.Image,
    template_landmarks: ArrayLike,
    mask: sitk.Image,
    *,
    n_points: int = 600,
    beta_mm: float = 6.0,
    lam: float = 2.0,
) -> np.ndarray:
    """Carry the template's landmarks onto another structure's boundary.

    Parameters
    ----------
    template_mask : 3D SimpleITK image
        Binary mask of the template shape.
    template_landmarks : (N, 3) float array, mm
        Landmarks on the template's boundary.
    mask : 3D SimpleITK image
        Binary mask of the structure to put the landmarks on (any geometry).
    n_points : int, default 600
        Boundary points of each shape used by the registration (farthest-point sample).
    beta_mm, lam : float
        Smoothness of the coherent-point-drift warp (kernel width in mm, weight).

    Returns
    -------
    landmarks : (N, 3) float array, mm
        On boundary voxel centres of ``mask``, in its physical space.
    """
    src_all = boundary_points(template_mask)
    dst_all = boundary_points(mask)
    src = src_all[farthest_point_sampling(src_all, min(n_points, len(src_all)))]
    dst = dst_all[farthest_point_sampling(dst_all, min(n_points, len(dst_all)))]
    tree = cKDTree(dst)
    best = None
    for init in principal_axes_candidates(src, dst):
        tf, err = icp_similarity(src, dst, init, dst_tree=tree)
        if best is None or err < best[1]:
            best = (tf, err)
    similarity = best[0]
    cpd = cpd_nonrigid(similarity(src), dst, beta=beta_mm, lam=lam)
    moved = cpd.warp(similarity(np.asarray(template_landmarks, dtype=float)))
    _, nearest = cKDTree(dst_all).query(moved)
    return dst_all[nearest]


def fold_landmarks(train, test, *, labels, n_landmarks: int | None, seed: int):
    """Training cohort with landmarks, and reference landmarks of the test cases.

    Parameters
    ----------
    train, test : Cohort
    labels : tuple of int
    n_landmarks : int or None
    seed : int

    Returns
    -------
    train : Cohort
        ``train`` itself when every case carries landmarks, else a copy whose cases carry
        the landmarks computed from their label maps (cases whose correspondence failed are
        left out).
    references : list of (N, 3) float array or None
        Per test case: its own landmarks, or the template's transferred onto its label map.
    """
    given = [case.load_landmarks() for case in train]
    if all(lm is not None for lm in given):
        return train, [case.load_landmarks() for case in test]
    try:
        from medseg.correspondence import landmarks_from_labels
    except ImportError as exc:  # pragma: no cover - until medseg.correspondence lands
        raise MedsegError(
            "this cohort has no landmarks and medseg.correspondence is not available to "
            "compute them from the label maps"
        ) from exc
    masks = [select_labels(case.load_label(), labels) for case in train]
    corr = landmarks_from_labels(masks, n_landmarks=n_landmarks, labels=(1,), random_state=seed)
    keep = ~np.asarray(corr.failed, dtype=bool)
    landmarks = np.asarray(corr.landmarks, dtype=float)
    cases = [
        dataclasses.replace(case, landmarks=landmarks[i]) for i, case in enumerate(train) if keep[i]
    ]
    ref = int(corr.reference_index)
    template_mask, template_landmarks = masks[ref], landmarks[ref]
    references = []
    for case in test:
        own = case.load_landmarks()
        if own is not None and own.shape == template_landmarks.shape:
            references.append(own)
        else:
            mask = select_labels(case.load_label(), labels)
            references.append(transfer_landmarks(template_mask, template_landmarks, mask))
    return dataclasses.replace(train, cases=cases), references
