"""Carrying reference landmarks onto one target surface: the registration chain.

For one target: principal-axes alignments of the reference (the 4 proper sign choices, or 8
with reflections), each refined by a similarity ICP, the best kept; then, in a frame where
the target is centred with unit RMS radius, an affine ICP and coherent point drift; finally
the warped reference landmarks are projected onto the target's triangles. The point-set
algorithms are :mod:`medseg.geometry`'s; this module only chains them.

:class:`_TransferOptions` is the one home of the defaults of the settings that
:func:`transfer_landmarks` and :func:`~medseg.correspondence.landmarks_from_labels` share
(both signatures read them from it), so that the two entries cannot drift apart.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from sklearn.utils import check_random_state
from threadpoolctl import threadpool_limits

from medseg.correspondence._surface import _closest_on_surface, _polydata, label_surface
from medseg.geometry import (
    Similarity,
    cpd_nonrigid,
    farthest_point_sampling,
    icp_affine,
    icp_similarity,
    principal_axes_candidates,
)


@dataclass(frozen=True)
class _TransferOptions:
    """Keyword settings of the transfer, with their defaults (documented, for users, in
    :func:`~medseg.correspondence.landmarks_from_labels`)."""

    keep_largest: bool = False
    allow_reflection: bool = False
    n_registration_points: int = 1000
    beta: float = 2.0
    lam: float = 2.0
    outlier_weight: float = 0.02
    affine: bool = True
    rank: int | None = 40

    def registration_sample(self, vertices: np.ndarray) -> np.ndarray:
        """The reference's registration points: a farthest-point subsample of its vertices."""
        n = min(self.n_registration_points, len(vertices))
        return vertices[farthest_point_sampling(vertices, n)]


_DEFAULT = _TransferOptions()


def _transfer(
    ref_vertices: np.ndarray,
    ref_sample: np.ndarray,
    ref_landmarks: np.ndarray,
    tgt_vertices: np.ndarray,
    tgt_faces: np.ndarray,
    *,
    options: _TransferOptions,
    seed: int,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Carry the reference landmarks onto one target surface.

    Returns the projected landmarks (N, 3) mm, the residual in mm and the (4, 4) similarity.
    """
    allow_reflection = options.allow_reflection
    # many small dense problems: BLAS / OpenMP threads would only contend (n_jobs does it)
    with threadpool_limits(limits=1):
        rng = check_random_state(seed)
        n_tgt = min(options.n_registration_points, len(tgt_vertices))
        tgt_sample = tgt_vertices[
            farthest_point_sampling(tgt_vertices, n_tgt, start=int(rng.randint(len(tgt_vertices))))
        ]
        tree = cKDTree(tgt_sample)
        best = None
        for init in principal_axes_candidates(
            ref_sample, tgt_sample, allow_reflection=allow_reflection
        ):
            tf, err = icp_similarity(
                ref_sample, tgt_sample, init, dst_tree=tree, allow_reflection=allow_reflection
            )
            if best is None or err < best[1]:
                best = (tf, err)
        sim: Similarity = best[0]
        # then affine, then non-rigid, in a normalised frame: target centred, unit RMS radius
        centre = tgt_sample.mean(0)
        radius = float(np.sqrt(((tgt_sample - centre) ** 2).sum(1).mean()))

        def norm(p):
            return (p - centre) / radius

        if options.affine:
            mat, vec, _ = icp_affine(norm(sim(ref_sample)), norm(tgt_sample))
        else:
            mat, vec = np.eye(3), np.zeros(3)

        def pre(p):
            return norm(sim(p)) @ mat.T + vec

        warped = _drift(
            pre(ref_sample), norm(tgt_sample), [pre(ref_landmarks), pre(ref_vertices)], options
        )
        warped_landmarks, warped_vertices = (w * radius + centre for w in warped)
        mesh = _polydata(tgt_vertices, tgt_faces)
        landmarks, _ = _closest_on_surface(mesh, warped_landmarks)
        _, dist = _closest_on_surface(mesh, warped_vertices)
    return landmarks, float(dist.mean()), sim.matrix()


def _drift(
    source: np.ndarray, target: np.ndarray, carried: list[np.ndarray], options: _TransferOptions
) -> list[np.ndarray]:
    """Coherent point drift of ``source`` onto ``target``, in the frame where the target is
    centred with unit RMS radius (the one ``beta`` and ``lam`` are set for); returns each
    array of ``carried`` moved by its displacement field."""
    cpd = cpd_nonrigid(
        source,
        target,
        beta=options.beta,
        lam=options.lam,
        w=options.outlier_weight,
        rank=options.rank,
    )
    return [cpd.warp(p) for p in carried]


def follow_boundary(
    landmarks: np.ndarray,
    source: tuple[np.ndarray, np.ndarray],
    target: tuple[np.ndarray, np.ndarray],
    *,
    n_points: int = 300,
) -> np.ndarray:
    """Landmarks on one surface, carried onto a nearby second surface.

    For a surface that has moved a little (a segmentation refined at its boundary): no
    global alignment, only the coherent point drift of :func:`transfer_landmarks` from a
    farthest-point sample of ``source`` onto one of ``target``, with its defaults, and the
    moved landmarks projected onto ``target``'s triangles. The drift is smooth and slides a
    little: on a 26 mm bean rasterised on a 1 mm grid and moved by 2-4 mm, the landmarks
    land 0.6-0.8 mm (median) from where the motion takes them, where projecting them
    straight onto the moved surface leaves 1.7-3.4 mm; grown by 5 %, about 1 mm (the
    chain's affine step did not help at this sampling).

    Parameters
    ----------
    landmarks : (N, 3) float array, mm
        On or near ``source``.
    source, target : ((V, 3) float array, (F, 3) int array)
        Triangle meshes in mm (e.g. :func:`label_surface`), in the same frame.
    n_points : int, default 300
        Points of each surface in the drift.

    Returns
    -------
    (N, 3) float array, mm
    """
    with threadpool_limits(limits=1):
        samples = []
        for vertices, _ in (source, target):
            vertices = np.asarray(vertices, dtype=float)
            samples.append(
                vertices[farthest_point_sampling(vertices, min(n_points, len(vertices)))]
            )
        centre = samples[1].mean(0)
        radius = float(np.sqrt(((samples[1] - centre) ** 2).sum(1).mean()))
        source_n, target_n, points_n = (
            (p - centre) / radius for p in (*samples, np.asarray(landmarks, dtype=float))
        )
        (moved,) = _drift(source_n, target_n, [points_n], _DEFAULT)
        moved = moved * radius + centre
        projected, _ = _closest_on_surface(_polydata(*target), moved)
    return projected


def transfer_landmarks(
    reference_surface: tuple[np.ndarray, np.ndarray],
    reference_landmarks: np.ndarray,
    label_map,
    *,
    labels: int | Sequence[int] = (1,),
    random_state=None,
    keep_largest: bool = _DEFAULT.keep_largest,
    allow_reflection: bool = _DEFAULT.allow_reflection,
    n_registration_points: int = _DEFAULT.n_registration_points,
    beta: float = _DEFAULT.beta,
    lam: float = _DEFAULT.lam,
    outlier_weight: float = _DEFAULT.outlier_weight,
    affine: bool = _DEFAULT.affine,
    rank: int | None = _DEFAULT.rank,
) -> np.ndarray:
    """Carry landmarks from a reference surface onto the boundary of one more label map.

    The transfer :func:`landmarks_from_labels` applies to each training case (principal
    axes + ICP similarity, affine ICP, coherent point drift, projection onto the target's
    triangles), with the same defaults, for a case that was not in the training set (e.g.
    the reference landmarks of a test case in cross-validation).

    Parameters
    ----------
    reference_surface : ((V, 3) float array, (F, 3) int array)
        Reference boundary, mm (``CorrespondenceResult.reference_surface``).
    reference_landmarks : (N, 3) float array, mm
        Landmarks on that boundary.
    label_map : SimpleITK image, nibabel image or path
        The structure to put the landmarks on (any geometry).
    labels : int or sequence of int, default (1,)
        As in :func:`landmarks_from_labels`.
    random_state : int, RandomState or None
    keep_largest, allow_reflection, n_registration_points, beta, lam, outlier_weight, \
affine, rank
        As in :func:`landmarks_from_labels`, with the same defaults.

    Returns
    -------
    landmarks : (N, 3) float array, mm
        On the boundary of ``label_map``, in its physical space.
    """
    opts = _TransferOptions(
        keep_largest=keep_largest, allow_reflection=allow_reflection,
        n_registration_points=n_registration_points, beta=beta, lam=lam,
        outlier_weight=outlier_weight, affine=affine, rank=rank,
    )  # fmt: skip
    ref_vertices = np.asarray(reference_surface[0], dtype=float)
    ref_sample = opts.registration_sample(ref_vertices)
    tgt_vertices, tgt_faces = label_surface(
        label_map, labels=labels, keep_largest=opts.keep_largest
    )
    seed = int(check_random_state(random_state).randint(np.iinfo(np.int32).max))
    landmarks, _, _ = _transfer(
        ref_vertices,
        ref_sample,
        np.asarray(reference_landmarks, dtype=float),
        tgt_vertices,
        tgt_faces,
        options=opts,
        seed=seed,
    )
    return landmarks
