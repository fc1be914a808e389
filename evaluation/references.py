"""Reference landmarks for cohorts that have none (real data: label maps only).

The phantom carries ground-truth landmarks per case; a real cohort such as the MSD
hippocampus does not. There, per fold:

* the training landmarks come from :func:`medseg.correspondence.landmarks_from_labels` on the
  training label maps, computed **once** and attached to the training cases, so every method
  of the fold (the segmenter, the detection baseline and the ASM) trains on the same
  landmarks;
* a test case's reference landmarks are the template's landmarks carried onto its label map
  by :func:`transfer_landmarks`: a similarity (principal axes + ICP over the boundary
  points), a non-rigid coherent-point-drift warp of the template boundary onto the test
  boundary, and a projection of each landmark onto the test boundary surface.

The landmark error on real data is therefore measured against a registration-derived
reference, not against expert landmarks: it is a consistency measure and is reported as such.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import pyvista as pv
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree
from sklearn.utils import check_random_state

from medseg._registration import (
    cpd_nonrigid,
    farthest_point_sampling,
    icp_similarity,
    principal_axes_candidates,
)
from medseg.correspondence import label_surface, landmarks_from_labels

__all__ = ["transfer_landmarks", "fold_landmarks"]


def transfer_landmarks(
    template_surface: tuple[np.ndarray, np.ndarray],
    template_landmarks: ArrayLike,
    label_map,
    *,
    labels: Sequence[int] = (1,),
    n_points: int = 600,
    beta: float = 0.8,
    lam: float = 1.0,
    outlier_weight: float = 0.02,
    random_state=None,
) -> np.ndarray:
    """Carry the template's landmarks onto another structure's boundary.

    The same steps as :func:`medseg.correspondence.landmarks_from_labels` uses for its
    training cases (that module has no public function for one new label map): boundary
    meshes, similarity by principal axes + ICP, non-rigid coherent point drift in a frame
    normalised to unit RMS radius, projection onto the target's triangles.

    Parameters
    ----------
    template_surface : ((V, 3) float array, (F, 3) int array)
        Template boundary, mm (``CorrespondenceResult.reference_surface``).
    template_landmarks : (N, 3) float array, mm
        Landmarks on the template's boundary.
    label_map : SimpleITK image or path
        Label map of the structure to put the landmarks on (any geometry).
    labels : sequence of int
        Labels forming the structure.
    n_points : int, default 600
        Boundary points of each shape used by the registration (farthest-point sample).
    beta, lam, outlier_weight : float
        Coherent point drift kernel width (normalised units), regularisation weight,
        outlier weight; the defaults of ``landmarks_from_labels``.
    random_state : int, RandomState or None

    Returns
    -------
    landmarks : (N, 3) float array, mm
        On the boundary surface of ``label_map``, in its physical space.
    """
    rng = check_random_state(random_state)
    src_vertices = np.asarray(template_surface[0], dtype=float)
    dst_vertices, dst_faces = label_surface(label_map, labels=tuple(labels), keep_largest=True)
    src = src_vertices[farthest_point_sampling(src_vertices, min(n_points, len(src_vertices)))]
    dst = dst_vertices[
        farthest_point_sampling(
            dst_vertices,
            min(n_points, len(dst_vertices)),
            start=int(rng.randint(len(dst_vertices))),
        )
    ]
    tree = cKDTree(dst)
    best = None
    for init in principal_axes_candidates(src, dst):
        tf, err = icp_similarity(src, dst, init, dst_tree=tree)
        if best is None or err < best[1]:
            best = (tf, err)
    similarity = best[0]
    centre = dst.mean(axis=0)
    radius = float(np.sqrt(((dst - centre) ** 2).sum(axis=1).mean()))
    cpd = cpd_nonrigid(
        (similarity(src) - centre) / radius,
        (dst - centre) / radius,
        beta=beta,
        lam=lam,
        w=outlier_weight,
    )
    moved = cpd.warp((similarity(np.asarray(template_landmarks, float)) - centre) / radius)
    moved = moved * radius + centre
    cells = np.hstack([np.full((len(dst_faces), 1), 3), dst_faces]).ravel()
    mesh = pv.PolyData(dst_vertices, cells)
    _, closest = mesh.find_closest_cell(moved, return_closest_point=True)
    return np.asarray(closest, dtype=float).reshape(-1, 3)


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
    corr = landmarks_from_labels(
        [case.load_label() for case in train],
        n_landmarks=n_landmarks,
        labels=tuple(labels),
        random_state=seed,
        keep_largest=True,
        case_ids=[case.case_id for case in train],
    )
    keep = ~np.asarray(corr.failed, dtype=bool)
    landmarks = np.asarray(corr.landmarks, dtype=float)
    cases = [
        dataclasses.replace(case, landmarks=landmarks[i]) for i, case in enumerate(train) if keep[i]
    ]
    template_landmarks = landmarks[int(corr.reference_index)]
    references = []
    for case in test:
        own = case.load_landmarks()
        if own is not None and own.shape == template_landmarks.shape:
            references.append(own)
        else:
            references.append(
                transfer_landmarks(
                    corr.reference_surface,
                    template_landmarks,
                    case.load_label(),
                    labels=labels,
                    random_state=seed,
                )
            )
    return dataclasses.replace(train, cases=cases), references
