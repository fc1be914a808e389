"""Landmarks in correspondence over a training cohort, and the result that lets one judge them.

:func:`landmarks_from_labels` is the cohort-level driver: surfaces of every case, the
reference case (medoid of the principal radii) and its farthest-point landmarks, then the
transfer onto every other case in parallel, one seed drawn per case up front so that the
result does not depend on ``n_jobs``. :func:`cohort_landmarks` returns the user's own
landmarks when every case has them and computes them otherwise.
:class:`CorrespondenceResult` keeps what is needed to judge the correspondence (residuals,
failures, surfaces, the rigid part of each transfer) and to draw it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from joblib import Parallel, delayed
from skimage.measure import mesh_surface_area
from sklearn.utils import check_random_state

from medseg.correspondence._surface import _as_label_image, _case_name, label_surface
from medseg.correspondence._transfer import _DEFAULT, _transfer, _TransferOptions
from medseg.errors import CohortError, MeshError
from medseg.geometry import farthest_point_sampling

#: at most one landmark per this many surface vertices (of the smallest training surface)
VERTICES_PER_LANDMARK = 4


@dataclass
class CorrespondenceResult:
    """Landmarks in correspondence, with what is needed to judge them.

    Attributes
    ----------
    landmarks : (S, N, 3) float array, mm, (x, y, z)
        Landmark ``n`` of every case is the same anatomical site; on each case's boundary.
    residuals_mm : (S,) float array
        Mean distance of the deformed reference surface to each case's surface (0 for the
        reference itself).
    failed : (S,) bool array
        ``residuals_mm > max_residual_mm``: the registration did not reach the surface.
    reference_index : int
        Case whose surface carries the reference landmarks.
    reference_surface : ((V, 3) float array, (F, 3) int array)
        Vertices (mm) and triangles of the reference boundary.
    reference_landmark_index : (N,) int array
        Indices of the reference landmarks into the reference vertices.
    surfaces : list of ((V_s, 3), (F_s, 3)) arrays
        Boundary of every case, mm.
    transforms : (S, 4, 4) float array
        Similarity from the reference frame to each case (homogeneous, column vectors), the
        rigid part of the transfer; used to show cases side by side.
    case_ids : list of str
    max_residual_mm : float
        Threshold used for ``failed``.
    """

    landmarks: np.ndarray
    residuals_mm: np.ndarray
    failed: np.ndarray
    reference_index: int
    reference_surface: tuple[np.ndarray, np.ndarray]
    reference_landmark_index: np.ndarray
    surfaces: list = field(repr=False)
    transforms: np.ndarray = field(repr=False)
    case_ids: list
    max_residual_mm: float

    @property
    def n_landmarks(self) -> int:
        return int(self.landmarks.shape[1])

    @property
    def success(self) -> bool:
        """True when no case failed."""
        return not bool(self.failed.any())


def _shape_descriptor(vertices: np.ndarray) -> np.ndarray:
    """Pose-free descriptor: log principal radii of the surface."""
    cov = np.cov((vertices - vertices.mean(0)).T)
    return 0.5 * np.log(np.maximum(np.sort(np.linalg.eigvalsh(cov)), 1e-12))


def _choose_reference(surfaces) -> int:
    desc = np.stack([_shape_descriptor(v) for v, _ in surfaces])
    dist = np.abs(desc[:, None, :] - desc[None, :, :]).sum(-1)
    return int(np.argmin(dist.sum(axis=1)))


def _default_n_landmarks(area_mm2: float, spacing_mm: float) -> int:
    # one landmark per (5 voxels)^2 of surface, within [12, 100]
    return int(np.clip(round(area_mm2 / (5.0 * spacing_mm) ** 2), 12, 100))


def landmarks_from_labels(
    label_maps: Sequence,
    *,
    n_landmarks: int | None = None,
    labels: int | Sequence[int] = (1,),
    reference: int | None = None,
    random_state=None,
    n_jobs: int = 1,
    max_residual_mm: float | None = None,
    case_ids: Sequence[str] | None = None,
    progress: bool = False,
    keep_largest: bool = _DEFAULT.keep_largest,
    allow_reflection: bool = _DEFAULT.allow_reflection,
    n_registration_points: int = _DEFAULT.n_registration_points,
    beta: float = _DEFAULT.beta,
    lam: float = _DEFAULT.lam,
    outlier_weight: float = _DEFAULT.outlier_weight,
    affine: bool = _DEFAULT.affine,
    rank: int | None = _DEFAULT.rank,
) -> CorrespondenceResult:
    """Landmarks in correspondence on the boundaries of training label maps.

    Parameters
    ----------
    label_maps : sequence of SimpleITK images (or nibabel images, or paths)
        One 3D label map per training case, any geometry (anisotropic, oblique).
    n_landmarks : int, optional
        N. Default: sized to the structure, one landmark per (5 voxels)^2 of the reference
        surface, between 12 and 100.
    labels : int or sequence of int, default (1,)
        The structure is the union of these labels (``(1, 2)`` for the MSD hippocampus).
    reference : int, optional
        Index of the reference case; default the case closest to the others (medoid of the
        principal radii of the surfaces).
    random_state : int, RandomState instance or None
        Seeds the surface subsampling of each case; results do not depend on ``n_jobs``.
    n_jobs : int, default 1
        Cases registered in parallel (joblib).
    max_residual_mm : float, optional
        A case fails when its residual exceeds this. Default: the mean voxel spacing of the
        label maps (a registration that does not reach the surface to within one voxel).
    case_ids : sequence of str, optional
        Names used in messages and in the result; default ``"0"``, ``"1"``, ...
    progress : bool, default False
        Show a tqdm progress bar.
    keep_largest : bool, default False
        Keep the largest part of a disconnected structure instead of raising
        :class:`~medseg.errors.LabelError` (parts under 1 % of the voxels are always dropped).
    allow_reflection : bool, default False
        Also try the 4 improper principal-axes alignments (mirror images), e.g. to put left
        and right organs in one correspondence.
    n_registration_points : int, default 1000
        Surface points per case used by the registration (farthest-point subsample).
    beta, lam, outlier_weight : float, default 2.0, 2.0, 0.02
        Coherent point drift: kernel width and regularisation (in units of the target's RMS
        radius), and weight of the uniform outlier term.
    affine : bool, default True
        An affine ICP between the similarity and the coherent point drift.
    rank : int or None, default 40
        Low-rank approximation of the coherent point drift kernel (None: exact).

    Returns
    -------
    CorrespondenceResult

    Raises
    ------
    CohortError
        No label maps, or ``reference`` out of range.
    LabelError
        A label map lacks ``labels`` or its structure is disconnected (message names it).
    MeshError
        ``n_landmarks`` is larger than the smallest surface supports (one landmark per
        ``VERTICES_PER_LANDMARK`` vertices).
    """
    from tqdm.auto import tqdm

    opts = _TransferOptions(
        keep_largest=keep_largest, allow_reflection=allow_reflection,
        n_registration_points=n_registration_points, beta=beta, lam=lam,
        outlier_weight=outlier_weight, affine=affine, rank=rank,
    )  # fmt: skip
    label_maps = list(label_maps)
    n_cases = len(label_maps)
    if n_cases == 0:
        raise CohortError("no label maps given: landmarks_from_labels needs at least one case")
    ids = [str(i) for i in range(n_cases)] if case_ids is None else [str(c) for c in case_ids]
    if len(ids) != n_cases:
        raise CohortError(f"{len(ids)} case_ids given for {n_cases} label maps")
    if reference is not None and not 0 <= int(reference) < n_cases:
        raise CohortError(f"`reference` must be a case index in [0, {n_cases}); got {reference}")
    rng = check_random_state(random_state)

    images = [_as_label_image(lm, _case_name(ids[i])) for i, lm in enumerate(label_maps)]
    surfaces = [
        label_surface(im, labels=labels, keep_largest=opts.keep_largest, case_id=ids[i])
        for i, im in enumerate(tqdm(images, desc="surfaces", disable=not progress))
    ]
    spacing = float(np.mean([np.mean(im.GetSpacing()) for im in images]))
    ref = _choose_reference(surfaces) if reference is None else int(reference)
    ref_vertices, ref_faces = surfaces[ref]
    if n_landmarks is None:
        area = mesh_surface_area(ref_vertices, ref_faces)
        n_landmarks = _default_n_landmarks(area, spacing)
    n_landmarks = int(n_landmarks)
    smallest = int(np.argmin([len(v) for v, _ in surfaces]))
    supported = len(surfaces[smallest][0]) // VERTICES_PER_LANDMARK
    if n_landmarks < 3:
        raise MeshError(f"`n_landmarks` must be at least 3; got {n_landmarks}")
    if n_landmarks > supported:
        raise MeshError(
            f"n_landmarks={n_landmarks} is more than the surface of "
            f"{_case_name(ids[smallest])} supports ({len(surfaces[smallest][0])} vertices: at "
            f"most {supported} landmarks). Use fewer landmarks or finer label maps."
        )
    threshold = spacing if max_residual_mm is None else float(max_residual_mm)

    ref_index = farthest_point_sampling(ref_vertices, n_landmarks)
    ref_landmarks = ref_vertices[ref_index]
    ref_sample = opts.registration_sample(ref_vertices)
    seeds = rng.randint(np.iinfo(np.int32).max, size=n_cases)
    todo = [i for i in range(n_cases) if i != ref]
    job = delayed(_transfer)
    tasks = (
        job(ref_vertices, ref_sample, ref_landmarks, *surfaces[i], options=opts, seed=int(seeds[i]))
        for i in todo
    )
    results = Parallel(n_jobs=n_jobs, return_as="generator")(tasks)
    landmarks = np.empty((n_cases, n_landmarks, 3))
    residuals = np.zeros(n_cases)
    transforms = np.tile(np.eye(4), (n_cases, 1, 1))
    landmarks[ref] = ref_landmarks
    bar = tqdm(results, total=len(todo), desc="correspondence", disable=not progress)
    for i, (lms, res, mat) in zip(todo, bar, strict=True):
        landmarks[i], residuals[i], transforms[i] = lms, res, mat
    return CorrespondenceResult(
        landmarks=landmarks,
        residuals_mm=residuals,
        failed=residuals > threshold,
        reference_index=ref,
        reference_surface=(ref_vertices, ref_faces),
        reference_landmark_index=ref_index,
        surfaces=surfaces,
        transforms=transforms,
        case_ids=ids,
        max_residual_mm=threshold,
    )


def cohort_landmarks(
    cohort,
    *,
    labels: int | Sequence[int] = (1,),
    use_given: bool = True,
    **kwargs,
) -> np.ndarray:
    """Landmarks of every case of a cohort: the user's own if given, else from the labels.

    Parameters
    ----------
    cohort : medseg.datasets.Cohort (or any sequence of cases)
        Cases with ``load_landmarks()`` and ``load_label()``.
    labels : int or sequence of int, default (1,)
        Structure used when the landmarks are computed.
    use_given : bool, default True
        If every case has landmarks (CSV / Slicer files, or arrays), return them unchanged
        and skip the correspondence step.
    **kwargs
        Passed to :func:`landmarks_from_labels`.

    Returns
    -------
    landmarks : (S, N, 3) float array, mm, (x, y, z)

    Raises
    ------
    CohortError
        Some cases have landmarks and others not, or the given landmark counts differ.
    """
    cases = list(cohort)
    given = [c.load_landmarks() for c in cases] if use_given else [None] * len(cases)
    have = [g is not None for g in given]
    if use_given and all(have) and cases:
        counts = {len(g) for g in given}
        if len(counts) != 1:
            raise CohortError(
                f"the cohort's landmark files hold different numbers of landmarks {sorted(counts)}"
                "; every case needs the same landmarks in the same order"
            )
        return np.stack([np.asarray(g, float) for g in given])
    if any(have) and use_given:
        missing = [c.case_id for c, h in zip(cases, have, strict=True) if not h][:5]
        raise CohortError(
            f"{sum(have)} of {len(cases)} cases have landmark files but others do not (e.g. "
            f"{missing}). Give landmarks for every case, or pass use_given=False to compute "
            "them all from the label maps."
        )
    kwargs.setdefault("case_ids", [c.case_id for c in cases])
    result = landmarks_from_labels([c.load_label() for c in cases], labels=labels, **kwargs)
    return result.landmarks
