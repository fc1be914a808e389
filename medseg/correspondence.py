"""Landmarks in correspondence from training label maps.

Users have label maps, not landmarks. :func:`landmarks_from_labels` turns the label maps of
one structure (or of a union of labels) into ``N`` boundary landmarks per case that
correspond across cases:

1. the boundary of each label map by marching cubes (scikit-image), in physical mm through
   :func:`medseg.io.voxel_to_physical` (anisotropic and oblique images are handled);
2. a reference case (the one closest to the others, or a given one) and ``N`` landmarks
   spread over its surface by farthest-point sampling;
3. for every other case, the reference surface is aligned by its principal axes (the 4
   proper sign choices, or 8 with reflections, each refined by a similarity ICP; the best
   kept), then deformed onto the case by coherent point drift (non-rigid), and the deformed
   reference landmarks are projected onto the case's surface.

The fit residual of each case is the mean distance of the deformed reference surface to the
case's surface; cases whose residual exceeds a threshold are flagged as failed.

References
----------
.. [1] A. Myronenko and X. Song, "Point set registration: coherent point drift", IEEE TPAMI
   32(12), 2010. :doi:`10.1109/TPAMI.2010.46`
.. [2] W. E. Lorensen and H. E. Cline, "Marching cubes", SIGGRAPH 1987; T. Lewiner et al.,
   "Efficient implementation of marching cubes' cases with topological guarantees",
   J. Graphics Tools 8(2), 2003. :doi:`10.1080/10867651.2003.10487582`
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pyvista as pv
import SimpleITK as sitk
from joblib import Parallel, delayed
from scipy import ndimage
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes, mesh_surface_area
from sklearn.utils import check_random_state
from threadpoolctl import threadpool_limits

from medseg.errors import CohortError, LabelError, MeshError
from medseg.geometry import (
    Similarity,
    cpd_nonrigid,
    farthest_point_sampling,
    icp_affine,
    icp_similarity,
    principal_axes_candidates,
)
from medseg.io import read_image, select_labels, voxel_to_physical

__all__ = [
    "CorrespondenceResult",
    "label_surface",
    "landmarks_from_labels",
    "cohort_landmarks",
    "transfer_landmarks",
    "plot_correspondences",
]

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


# ---------------------------------------------------------------------- surfaces


def _case_name(case_id: str | None, index: int | None = None) -> str:
    if case_id is not None:
        return f"case {case_id!r}"
    return f"label map #{index}" if index is not None else "label map"


def _as_label_image(source, name: str) -> sitk.Image:
    image = source if isinstance(source, sitk.Image) else read_image(source)
    if image.GetDimension() != 3:
        raise LabelError(f"{name}: expected a 3D label map, got {image.GetDimension()}D")
    return image


def _single_component(mask: np.ndarray, name: str, keep_largest: bool, min_fraction: float):
    """Boolean mask of the one significant 6-connected component; tiny specks are dropped."""
    lab, n = ndimage.label(mask)
    if n <= 1:
        return mask
    sizes = np.bincount(lab.ravel())[1:]
    order = np.argsort(sizes)[::-1]
    significant = sizes >= min_fraction * sizes.sum()
    if significant.sum() > 1 and not keep_largest:
        listed = ", ".join(str(int(s)) for s in sizes[order][:6])
        raise LabelError(
            f"{name}: the structure is split into {int(significant.sum())} disconnected parts "
            f"of significant size (component sizes in voxels: {listed}). Fix the label map, "
            "choose the labels of one structure, or pass keep_largest=True to keep only the "
            "largest part."
        )
    return lab == order[0] + 1


def label_surface(
    label_map,
    *,
    labels: int | Sequence[int] = (1,),
    keep_largest: bool = False,
    min_component_fraction: float = 0.01,
    smoothing: float = 0.5,
    case_id: str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Boundary of a structure in a label map, as a triangle mesh in physical mm.

    Parameters
    ----------
    label_map : SimpleITK image, nibabel image or path
        3D integer label map.
    labels : int or sequence of int
        The structure is the union of these labels, e.g. ``(1, 2)`` for the MSD hippocampus.
    keep_largest : bool, default False
        If the structure has several disconnected parts of significant size, keep the
        largest instead of raising :class:`~medseg.errors.LabelError`.
    min_component_fraction : float, default 0.01
        Parts smaller than this fraction of the structure's voxels are specks and are dropped
        silently.
    smoothing : float, default 0.5
        Standard deviation, in voxels, of the Gaussian applied to the binary mask before
        marching cubes at level 0.5 (removes the staircase; 0 disables).
    case_id : str, optional
        Named in error messages.

    Returns
    -------
    vertices : (V, 3) float array, mm, (x, y, z)
        In the image's world frame (through :func:`medseg.io.voxel_to_physical`).
    faces : (F, 3) int array
        Triangles, oriented with outward normals.

    Raises
    ------
    LabelError
        No voxel carries ``labels``, or the structure is disconnected.
    """
    name = _case_name(case_id)
    image = _as_label_image(label_map, name)
    try:
        mask_img = select_labels(image, labels)
    except LabelError as exc:
        raise LabelError(f"{name}: {exc}") from None
    mask = sitk.GetArrayViewFromImage(mask_img).astype(bool)
    mask = _single_component(mask, name, keep_largest, min_component_fraction)
    vol = np.pad(mask.astype(np.float32), 2)
    if smoothing > 0:
        vol = ndimage.gaussian_filter(vol, sigma=float(smoothing))
    if vol.max() <= 0.5:
        raise LabelError(f"{name}: the structure is too thin to have a boundary at level 0.5")
    verts, faces, _, _ = marching_cubes(vol, level=0.5, allow_degenerate=False)
    verts = voxel_to_physical(image, verts - 2.0)
    faces = faces.astype(np.int64)
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    signed_volume = np.einsum("ij,ij->", v0, np.cross(v1, v2)) / 6.0
    if signed_volume < 0:
        faces = faces[:, ::-1].copy()
    return verts, faces


# ---------------------------------------------------------------------- registration


def _shape_descriptor(vertices: np.ndarray) -> np.ndarray:
    """Pose-free descriptor: log principal radii of the surface."""
    cov = np.cov((vertices - vertices.mean(0)).T)
    return 0.5 * np.log(np.maximum(np.sort(np.linalg.eigvalsh(cov)), 1e-12))


def _choose_reference(surfaces) -> int:
    desc = np.stack([_shape_descriptor(v) for v, _ in surfaces])
    dist = np.abs(desc[:, None, :] - desc[None, :, :]).sum(-1)
    return int(np.argmin(dist.sum(axis=1)))


def _closest_on_surface(mesh: pv.PolyData, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points on the triangles of ``mesh`` and their distances."""
    _, closest = mesh.find_closest_cell(np.asarray(points, float), return_closest_point=True)
    closest = np.asarray(closest, float).reshape(-1, 3)
    return closest, np.linalg.norm(closest - points, axis=1)


def _polydata(vertices: np.ndarray, faces: np.ndarray) -> pv.PolyData:
    cells = np.hstack([np.full((len(faces), 1), 3), faces]).ravel()
    return pv.PolyData(np.asarray(vertices, float), cells)


def _transfer(
    ref_vertices: np.ndarray,
    ref_sample: np.ndarray,
    ref_landmarks: np.ndarray,
    tgt_vertices: np.ndarray,
    tgt_faces: np.ndarray,
    *,
    n_points: int,
    allow_reflection: bool,
    beta: float,
    lam: float,
    outlier_weight: float,
    seed: int,
    affine: bool,
    rank: int | None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Carry the reference landmarks onto one target surface.

    Returns the projected landmarks (N, 3) mm, the residual in mm and the (4, 4) similarity.
    """
    # many small dense problems: BLAS / OpenMP threads would only contend (n_jobs does it)
    with threadpool_limits(limits=1):
        rng = check_random_state(seed)
        n_tgt = min(n_points, len(tgt_vertices))
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

        tgt_n = norm(tgt_sample)
        src_n = norm(sim(ref_sample))
        if affine:
            mat, vec, _ = icp_affine(src_n, tgt_n)
        else:
            mat, vec = np.eye(3), np.zeros(3)

        def pre(p):
            return norm(sim(p)) @ mat.T + vec

        cpd = cpd_nonrigid(pre(ref_sample), tgt_n, beta=beta, lam=lam, w=outlier_weight, rank=rank)
        warped_vertices = cpd.warp(pre(ref_vertices)) * radius + centre
        warped_landmarks = cpd.warp(pre(ref_landmarks)) * radius + centre
        mesh = _polydata(tgt_vertices, tgt_faces)
        landmarks, _ = _closest_on_surface(mesh, warped_landmarks)
        _, dist = _closest_on_surface(mesh, warped_vertices)
    return landmarks, float(dist.mean()), sim.matrix()


def transfer_landmarks(
    reference_surface: tuple[np.ndarray, np.ndarray],
    reference_landmarks: np.ndarray,
    label_map,
    *,
    labels: int | Sequence[int] = (1,),
    keep_largest: bool = False,
    allow_reflection: bool = False,
    n_registration_points: int = 1000,
    beta: float = 2.0,
    lam: float = 2.0,
    outlier_weight: float = 0.02,
    affine: bool = True,
    rank: int | None = 40,
    random_state=None,
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
    labels, keep_largest, allow_reflection, n_registration_points, beta, lam,
    outlier_weight, affine, rank
        As in :func:`landmarks_from_labels`.
    random_state : int, RandomState or None

    Returns
    -------
    landmarks : (N, 3) float array, mm
        On the boundary of ``label_map``, in its physical space.
    """
    ref_vertices = np.asarray(reference_surface[0], dtype=float)
    ref_sample = ref_vertices[
        farthest_point_sampling(ref_vertices, min(n_registration_points, len(ref_vertices)))
    ]
    tgt_vertices, tgt_faces = label_surface(label_map, labels=labels, keep_largest=keep_largest)
    seed = int(check_random_state(random_state).randint(np.iinfo(np.int32).max))
    landmarks, _, _ = _transfer(
        ref_vertices,
        ref_sample,
        np.asarray(reference_landmarks, dtype=float),
        tgt_vertices,
        tgt_faces,
        n_points=n_registration_points,
        allow_reflection=allow_reflection,
        beta=beta,
        lam=lam,
        outlier_weight=outlier_weight,
        seed=seed,
        affine=affine,
        rank=rank,
    )
    return landmarks


# ---------------------------------------------------------------------- main entry


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
    keep_largest: bool = False,
    allow_reflection: bool = False,
    n_registration_points: int = 1000,
    beta: float = 2.0,
    lam: float = 2.0,
    outlier_weight: float = 0.02,
    affine: bool = True,
    rank: int | None = 40,
    max_residual_mm: float | None = None,
    case_ids: Sequence[str] | None = None,
    progress: bool = False,
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
    keep_largest : bool, default False
        Keep the largest part of a disconnected structure instead of raising
        :class:`~medseg.errors.LabelError` (parts under 1 % of the voxels are always dropped).
    allow_reflection : bool, default False
        Also try the 4 improper principal-axes alignments (mirror images), e.g. to put left
        and right organs in one correspondence.
    n_registration_points : int, default 1000
        Surface points per case used by the registration (farthest-point subsample).
    beta, lam, outlier_weight : float
        Coherent point drift: kernel width and regularisation (in units of the target's RMS
        radius), and weight of the uniform outlier term.
    max_residual_mm : float, optional
        A case fails when its residual exceeds this. Default: the mean voxel spacing of the
        label maps (a registration that does not reach the surface to within one voxel).
    case_ids : sequence of str, optional
        Names used in messages and in the result; default ``"0"``, ``"1"``, ...
    progress : bool, default False
        Show a tqdm progress bar.

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
        label_surface(im, labels=labels, keep_largest=keep_largest, case_id=ids[i])
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
    ref_sample = ref_vertices[
        farthest_point_sampling(ref_vertices, min(n_registration_points, len(ref_vertices)))
    ]
    seeds = rng.randint(np.iinfo(np.int32).max, size=n_cases)
    todo = [i for i in range(n_cases) if i != ref]
    job = delayed(_transfer)
    kwargs = dict(
        n_points=n_registration_points,
        allow_reflection=allow_reflection,
        beta=beta,
        lam=lam,
        outlier_weight=outlier_weight,
        affine=affine,
        rank=rank,
    )
    tasks = (
        job(ref_vertices, ref_sample, ref_landmarks, *surfaces[i], seed=int(seeds[i]), **kwargs)
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


# ---------------------------------------------------------------------- figure


def plot_correspondences(
    result: CorrespondenceResult,
    path: str | os.PathLike,
    *,
    n_cases: int = 4,
    cases: Sequence[int] | None = None,
    dpi: int = 120,
):
    """PNG of the landmarks on a few training surfaces, in the same colour order.

    Each case is drawn in the reference frame (its similarity to the reference undone) so the
    views are comparable; landmark ``n`` has the same colour in every panel.

    Parameters
    ----------
    result : CorrespondenceResult
    path : path-like
        PNG file, written atomically.
    n_cases : int, default 4
        Panels: the reference and the next cases in order (ignored if ``cases`` given).
    cases : sequence of int, optional
        Which cases to draw.

    Returns
    -------
    pathlib.Path
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from medseg.io import atomic_write

    n_total = len(result.surfaces)
    if cases is None:
        others = [i for i in range(n_total) if i != result.reference_index]
        cases = [result.reference_index] + others[: max(0, int(n_cases) - 1)]
    cases = [int(c) for c in cases]
    colours = plt.get_cmap("turbo")(np.linspace(0.05, 0.95, result.n_landmarks))
    # a common view: the reference's principal axes (longest along x, shortest towards the eye)
    ref_v = result.reference_surface[0]
    centre = ref_v.mean(0)
    _, axes = np.linalg.eigh(np.cov((ref_v - centre).T))
    axes = axes[:, ::-1] * np.array([1.0, 1.0, np.linalg.det(axes[:, ::-1])])
    fig = plt.figure(figsize=(3.4 * len(cases), 3.9))
    for panel, c in enumerate(cases):
        mat = result.transforms[c]
        inv = np.linalg.inv(mat[:3, :3])

        def view(p, mat=mat, inv=inv):
            return ((np.asarray(p) - mat[:3, 3]) @ inv.T - centre) @ axes

        verts, faces = result.surfaces[c]
        v = view(verts)
        lm = view(result.landmarks[c])
        ax = fig.add_subplot(1, len(cases), panel + 1, projection="3d", computed_zorder=False)
        ax.plot_trisurf(v[:, 0], v[:, 1], v[:, 2], triangles=faces, color="0.75", alpha=0.35,
                        linewidth=0, shade=True, zorder=1)  # fmt: skip
        ax.scatter(lm[:, 0], lm[:, 1], lm[:, 2], c=colours, s=30, depthshade=False,
                   edgecolors="k", linewidths=0.4, zorder=2, alpha=1.0)  # fmt: skip
        tag = " (reference)" if c == result.reference_index else ""
        ax.set_title(
            f"{result.case_ids[c]}{tag}\nresidual {result.residuals_mm[c]:.2f} mm", fontsize=8
        )
        half = np.abs(v).max() * 0.75
        ax.set_xlim(-half, half)
        ax.set_ylim(-half, half)
        ax.set_zlim(-half, half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=55, azim=-90)
        ax.set_axis_off()
    fig.suptitle(
        f"{result.n_landmarks} landmarks in correspondence: same colour = same landmark "
        "(cases shown in the reference frame)",
        fontsize=9,
        y=0.99,
    )
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.86, wspace=0)
    from pathlib import Path

    with atomic_write(Path(path)) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)
    return Path(path)
