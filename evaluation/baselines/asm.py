"""The standard active shape model (Cootes, Taylor, Cooper & Graham, 1995), in 3D.

What a user of ASM would run as a baseline, written from the paper:

1. **Point distribution model.** The training landmark sets are aligned by generalised
   Procrustes analysis (similarity transforms, unit centroid size, projection onto the
   tangent space of the mean); PCA of the aligned shapes keeps the modes that explain 98 %
   of the variance, and shape parameters are limited to +-3 sqrt(lambda).
2. **Grey-level profile models.** A fixed triangle mesh over the landmarks (the convex hull
   of the mean shape's landmarks projected onto a sphere around its centroid: valid for
   star-shaped structures) gives each landmark a normal in any instance. Along that normal,
   the image derivative is sampled at ``2k+1`` positions, normalised by the sum of its
   absolute values; per landmark and resolution level, the mean profile and a Ledoit-Wolf
   covariance give the Mahalanobis fit of a profile.
3. **Multi-resolution search** over a Gaussian scale space (the image smoothed with a
   sigma that doubles per level, the profile step doubling with it; coarse to fine). The
   search starts from the mean shape at the physical centre of the image, with unit pose:
   the mean training orientation and the mean training size. Each iteration moves every
   landmark along its normal to the best-fitting profile position among ``2(m-k)+1``
   offsets, then fits pose and shape parameters to the suggested points (similarity
   alignment, tangent projection, clamped parameters). A level ends when 90 % of the
   landmarks moved by at most one profile step, or after ``max_iter`` iterations.

The label map comes from the same thin-plate-spline reconstruction as the segmenter
(:func:`medseg.reconstruction.warp_mask`) with the training case closest to the mean shape
as template.

References
----------
T. F. Cootes, C. J. Taylor, D. H. Cooper, J. Graham, "Active shape models - their training
and application", Computer Vision and Image Understanding 61(1), 1995.
doi:10.1006/cviu.1995.1004

T. F. Cootes, C. J. Taylor, A. Lanitis, "Active shape models: evaluation of a
multi-resolution method for improving image search", BMVC 1994. doi:10.5244/C.8.32
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk
from scipy.ndimage import gaussian_filter, map_coordinates
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation
from sklearn.covariance import LedoitWolf
from tqdm.auto import tqdm

from medseg.errors import CohortError, NotFittedError
from medseg.io import physical_to_voxel, read_image, select_labels, voxel_to_physical
from medseg.reconstruction import warp_mask

__all__ = [
    "ActiveShapeModel",
    "ASMResult",
    "PointDistributionModel",
    "point_distribution_model",
    "landmark_mesh",
    "vertex_normals",
]

MIN_TRAINING_SHAPES = 3


# ----------------------------------------------------------------------------- geometry


def _similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares ``dst ~ s R src + t`` (proper rotation): (s, R, t)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a)
    d = np.array([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rot = (u * d) @ vt
    var = float((a**2).sum())
    s = float((sig * d).sum() / var) if var > 0 else 1.0
    return s, rot, mu_d - s * mu_s @ rot.T


def _align_all(shapes: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """Centred shapes aligned onto ``mean`` (similarity), projected onto its tangent space."""
    out = []
    for x in shapes:
        s, rot, _ = _similarity(x, mean)
        y = s * x @ rot.T
        out.append(y / np.sum(y * mean))
    return np.stack(out)


def landmark_mesh(shape: np.ndarray) -> np.ndarray:
    """Triangles over landmarks: the hull of the landmarks projected onto a sphere.

    Parameters
    ----------
    shape : (N, 3) float array
        A landmark configuration (the mean shape), star-shaped about its centroid.

    Returns
    -------
    faces : (F, 3) int array
        Oriented so that face normals point away from the centroid.
    """
    centred = shape - shape.mean(0)
    unit = centred / np.maximum(np.linalg.norm(centred, axis=1, keepdims=True), 1e-12)
    faces = ConvexHull(unit).simplices.copy()
    a, b, c = (unit[faces[:, j]] for j in range(3))
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), a + b + c) < 0
    faces[flip] = faces[flip][:, ::-1]
    return faces


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, ``(N, 3)``, of a landmark mesh."""
    a, b, c = (points[faces[:, j]] for j in range(3))
    fn = np.cross(b - a, c - a)
    normals = np.zeros_like(points)
    for j in range(3):
        np.add.at(normals, faces[:, j], fn)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


@dataclass(frozen=True)
class PointDistributionModel:
    """Result of :func:`point_distribution_model`.

    Attributes
    ----------
    mean : (N, 3) float array
        Mean shape: centred, unit centroid size, in the mean orientation of the inputs.
    modes : (K, N, 3) float array
        Orthonormal modes of variation (as flattened vectors).
    eigenvalues : (K,) float array
        Variance along each mode (unit-size frame), descending.
    mean_size : float
        Mean centroid size of the input shapes (their units, mm).
    aligned : (S, N, 3) float array
        Input shapes after Procrustes alignment and tangent projection.
    explained : float
        Fraction of the total variance the K modes explain.
    """

    mean: np.ndarray
    modes: np.ndarray
    eigenvalues: np.ndarray
    mean_size: float
    aligned: np.ndarray
    explained: float


def point_distribution_model(
    shapes: np.ndarray, *, variance: float = 0.98, max_iter: int = 50
) -> PointDistributionModel:
    """Generalised Procrustes alignment and PCA of landmark configurations.

    Parameters
    ----------
    shapes : (S, N, 3) float array, mm
        Landmark configurations in correspondence.
    variance : float, default 0.98
        Keep the fewest modes that explain at least this fraction of the variance.
    max_iter : int, default 50
        Procrustes iterations (the mean is re-estimated and re-aligned each time).

    Returns
    -------
    PointDistributionModel
        Invariant to a similarity transform of any input shape, except for the orientation
        of the mean, which is the mean (chordal L2) rotation of the inputs.
    """
    shapes = np.asarray(shapes, dtype=float)
    if shapes.ndim != 3 or shapes.shape[2] != 3 or len(shapes) < 2:
        raise ValueError(f"`shapes` must be (S, N, 3) with S >= 2, got {shapes.shape}")
    centred = shapes - shapes.mean(axis=1, keepdims=True)
    sizes = np.sqrt((centred**2).sum(axis=(1, 2)))
    unit = centred / sizes[:, None, None]
    mean = unit[0].copy()
    for _ in range(max_iter):
        new = _align_all(unit, mean).mean(axis=0)
        new /= np.linalg.norm(new)
        new = new @ _similarity(new, mean)[1].T  # keep the mean's orientation fixed
        converged = np.abs(new - mean).max() < 1e-10
        mean = new
        if converged:
            break
    # Unit pose = the mean orientation of the inputs: rotate the mean into it.
    rotations = Rotation.from_matrix(np.stack([_similarity(mean, x)[1] for x in unit]))
    mean = mean @ rotations.mean().as_matrix().T
    aligned = _align_all(unit, mean)
    dev = (aligned - mean).reshape(len(aligned), -1)
    _, sv, vt = np.linalg.svd(dev, full_matrices=False)
    eig = sv**2 / (len(aligned) - 1)
    total = eig.sum()
    if total > 0:
        ratio = np.cumsum(eig) / total
        k = min(int(np.searchsorted(ratio, variance - 1e-12) + 1), len(eig))
        explained = float(ratio[k - 1])
    else:
        k, explained = 0, 1.0
    return PointDistributionModel(
        mean=mean,
        modes=vt[:k].reshape(k, -1, 3),
        eigenvalues=eig[:k],
        mean_size=float(sizes.mean()),
        aligned=aligned,
        explained=explained,
    )


# ----------------------------------------------------------------------------- profiles


def _smoothed(image: sitk.Image, sigma_mm: float) -> np.ndarray:
    arr = sitk.GetArrayFromImage(image).astype(np.float32)
    spacing_zyx = np.asarray(image.GetSpacing(), dtype=float)[::-1]
    return gaussian_filter(arr, sigma=sigma_mm / spacing_zyx, mode="nearest")


def _profiles(
    image: sitk.Image,
    array: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    half: int,
    step: float,
) -> np.ndarray:
    """Derivative profiles ``(N, 2*half+1)`` along the normals, centred on the points.

    Intensities are sampled at offsets ``(j - 0.5) step`` for ``j = -half .. half+1`` and
    differenced, so value ``j`` is the derivative at offset ``j * step`` (mm).
    """
    offsets = (np.arange(-half, half + 2) - 0.5) * step
    samples = points[:, None, :] + offsets[None, :, None] * normals[:, None, :]
    zyx = physical_to_voxel(image, samples.reshape(-1, 3))
    values = map_coordinates(array, zyx.T, order=1, mode="nearest")
    return np.diff(values.reshape(len(points), -1), axis=1)


def _normalise(g: np.ndarray) -> np.ndarray:
    return g / np.maximum(np.abs(g).sum(axis=-1, keepdims=True), 1e-9)


# ----------------------------------------------------------------------------- model


@dataclass
class ASMResult:
    """The result of :meth:`ActiveShapeModel.segment`.

    Attributes
    ----------
    label : SimpleITK image, uint8
        The template carried onto ``landmarks`` (TPS), on the input's grid.
    landmarks : (N, 3) float array, mm
    shape_parameters : (K,) float array
        Final mode weights ``b``.
    pose : dict
        ``scale`` (mm, centroid size), ``rotation`` (3, 3), ``translation`` (3,) mm.
    n_iter : list of int
        Iterations per level, coarse to fine.
    mrf : None
        No MRF (present so that evaluation code treats every method alike).
    timings : dict
    """

    label: sitk.Image
    landmarks: np.ndarray
    shape_parameters: np.ndarray
    pose: dict
    n_iter: list
    mrf: None = None
    timings: dict = field(default_factory=dict)


class ActiveShapeModel:
    """Active shape model baseline (Cootes et al. 1995), multi-resolution, in 3D.

    Parameters
    ----------
    labels : tuple of int, default (1,)
        Labels of the training label maps forming the structure.
    variance : float, default 0.98
        Fraction of the shape variance the retained modes explain.
    limit : float, default 3.0
        Shape parameters are clamped to ``+-limit * sqrt(lambda)``.
    profile_half : int, default 3
        ``k``: the profile model has ``2k+1`` samples.
    search_half : int, default 6
        ``m > k``: the search profile has ``2m+1`` samples, i.e. ``2(m-k)+1`` offsets.
    step_mm : float, default 1.0
        Profile sample spacing at the finest level (doubles per coarser level).
    n_levels : int, default 3
        Resolution levels of the Gaussian scale space.
    max_iter : int, default 20
        Iterations per level.
    smoothing : float, default 0.0
        Thin-plate spline smoothing of the reconstruction.
    random_state : ignored
        Accepted for a uniform interface; nothing in the ASM is random.

    Attributes
    ----------
    mean_shape_ : (N, 3) float array
        Mean shape, unit centroid size, centred, in the mean training orientation.
    modes_ : (K, N, 3) float array
        Orthonormal shape modes (unit-size frame).
    eigenvalues_ : (K,) float array
    mean_size_ : float
        Mean centroid size of the training shapes (mm).
    faces_ : (F, 3) int array
        Triangles over the landmarks used for normals.
    profile_means_ : list over levels of (N, 2k+1) float arrays
    profile_precisions_ : list over levels of (N, 2k+1, 2k+1) float arrays
    template_mask_ : SimpleITK image
    template_landmarks_ : (N, 3) float array, mm
    """

    def __init__(
        self,
        *,
        labels: tuple[int, ...] = (1,),
        variance: float = 0.98,
        limit: float = 3.0,
        profile_half: int = 3,
        search_half: int = 6,
        step_mm: float = 1.0,
        n_levels: int = 3,
        max_iter: int = 20,
        smoothing: float = 0.0,
        random_state=None,
    ):
        self.labels = labels
        self.variance = variance
        self.limit = limit
        self.profile_half = profile_half
        self.search_half = search_half
        self.step_mm = step_mm
        self.n_levels = n_levels
        self.max_iter = max_iter
        self.smoothing = smoothing
        self.random_state = random_state

    # -- training ---------------------------------------------------------------------------

    _converged_shift = 1  # profile steps; a level ends when 90 % of moves are this small

    def _level_sigma_step(self, level: int) -> tuple[float, float]:
        step = self.step_mm * 2.0**level
        return 0.6 * step, step

    def fit(self, cohort, *, progress: bool = False) -> ActiveShapeModel:
        """Learn the point distribution model and the profile models.

        Parameters
        ----------
        cohort : Cohort
            Cases with images, label maps and landmarks ``(N, 3)`` mm in correspondence
            (``case.load_landmarks()``).
        progress : bool, default False
        """
        if not 0.0 < self.variance <= 1.0:
            raise ValueError("`variance` must be in (0, 1].")
        if self.search_half <= self.profile_half or self.profile_half < 1:
            raise ValueError("need 1 <= `profile_half` < `search_half`.")
        shapes, images = [], []
        for case in cohort:
            lm = case.load_landmarks()
            if lm is None:
                raise CohortError(
                    f"case {case.case_id!r} has no landmarks: the ASM trains on landmarks in "
                    "correspondence (give landmark files, or run it through medseg-evaluate, "
                    "which computes them from the label maps)"
                )
            shapes.append(np.asarray(lm, dtype=float))
            images.append(case)
        if len(shapes) < MIN_TRAINING_SHAPES:
            raise CohortError(
                f"the ASM needs at least {MIN_TRAINING_SHAPES} training shapes, got {len(shapes)}"
            )
        if len({s.shape for s in shapes}) != 1:
            raise CohortError("training cases carry different numbers of landmarks")
        shapes = np.stack(shapes)
        self._fit_shape_model(shapes)
        self._fit_profiles(cohort, shapes, progress)
        return self

    def _fit_shape_model(self, shapes: np.ndarray) -> None:
        pdm = point_distribution_model(shapes, variance=self.variance)
        self.mean_shape_ = pdm.mean
        self.modes_ = pdm.modes
        self.eigenvalues_ = pdm.eigenvalues
        self.mean_size_ = pdm.mean_size
        self.faces_ = landmark_mesh(pdm.mean)
        self._template_index = int(np.argmin(((pdm.aligned - pdm.mean) ** 2).sum(axis=(1, 2))))

    def _fit_profiles(self, cohort, shapes: np.ndarray, progress: bool) -> None:
        k = self.profile_half
        per_level: list[list[np.ndarray]] = [[] for _ in range(self.n_levels)]
        for i, case in enumerate(tqdm(cohort, desc="ASM profiles", disable=not progress)):
            image = read_image(case.load_image())
            normals = vertex_normals(shapes[i], self.faces_)
            for level in range(self.n_levels):
                sigma, step = self._level_sigma_step(level)
                arr = _smoothed(image, sigma)
                per_level[level].append(
                    _normalise(_profiles(image, arr, shapes[i], normals, k, step))
                )
            if i == self._template_index:
                self.template_mask_ = select_labels(case.load_label(), self.labels)
                self.template_landmarks_ = shapes[i].copy()
        self.profile_means_, self.profile_precisions_ = [], []
        for level in range(self.n_levels):
            g = np.stack(per_level[level], axis=1)  # (N, S, 2k+1)
            self.profile_means_.append(g.mean(axis=1))
            self.profile_precisions_.append(
                np.stack([LedoitWolf().fit(g_i).precision_ for g_i in g])
            )

    # -- search -----------------------------------------------------------------------------

    def _instance(self, b: np.ndarray) -> np.ndarray:
        return self.mean_shape_ + np.tensordot(b, self.modes_, axes=1)

    def _fit_to_points(
        self, y: np.ndarray, b: np.ndarray
    ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """Pose and clamped shape parameters that best explain suggested points ``y``."""
        limits = self.limit * np.sqrt(self.eigenvalues_)
        for _ in range(5):
            s, rot, t = _similarity(self._instance(b), y)
            local = ((y - t) @ rot) / s
            local = local / np.sum(local * self.mean_shape_)
            b_new = np.clip(
                np.tensordot(self.modes_, local - self.mean_shape_, axes=([1, 2], [0, 1])),
                -limits,
                limits,
            )
            if np.abs(b_new - b).max(initial=0.0) < 1e-6:
                b = b_new
                break
            b = b_new
        s, rot, t = _similarity(self._instance(b), y)
        return s, rot, t, b

    def segment(self, image, **_ignored) -> ASMResult:
        """Search the image from the mean shape at its centre, with unit pose.

        Parameters
        ----------
        image : path, SimpleITK image or nibabel image

        Returns
        -------
        ASMResult
        """
        if not hasattr(self, "profile_means_"):
            raise NotFittedError("this ActiveShapeModel is not fitted yet: call fit(cohort)")
        t_start = time.perf_counter()
        image = read_image(image)
        size_zyx = np.asarray(image.GetSize(), dtype=float)[::-1]
        centre = voxel_to_physical(image, ((size_zyx - 1.0) / 2.0)[None, :])[0]
        s, rot, t = self.mean_size_, np.eye(3), centre
        b = np.zeros(len(self.eigenvalues_))
        k, m = self.profile_half, self.search_half
        shifts = np.arange(-(m - k), m - k + 1)
        n_iter = []
        for level in reversed(range(self.n_levels)):
            sigma, step = self._level_sigma_step(level)
            arr = _smoothed(image, sigma)
            mean_g = self.profile_means_[level]
            prec = self.profile_precisions_[level]
            it = 0
            for it in range(1, self.max_iter + 1):  # noqa: B007
                x = s * self._instance(b) @ rot.T + t
                normals = vertex_normals(x, self.faces_)
                long = _profiles(image, arr, x, normals, m, step)  # (N, 2m+1)
                windows = np.stack([long[:, d + m - k : d + m + k + 1] for d in shifts], axis=1)
                diff = _normalise(windows) - mean_g[:, None, :]
                cost = np.einsum("nsi,nij,nsj->ns", diff, prec, diff)
                best = shifts[np.argmin(cost, axis=1)]
                y = x + (best * step)[:, None] * normals
                s, rot, t, b = self._fit_to_points(y, b)
                if np.mean(np.abs(best) <= self._converged_shift) >= 0.9:
                    break
            n_iter.append(it)
        landmarks = s * self._instance(b) @ rot.T + t
        timings = {"search": time.perf_counter() - t_start}
        t0 = time.perf_counter()
        label = warp_mask(
            self.template_mask_,
            self.template_landmarks_,
            landmarks,
            image,
            smoothing=self.smoothing,
        )
        timings["reconstruction"] = time.perf_counter() - t0
        return ASMResult(
            label=label,
            landmarks=landmarks,
            shape_parameters=b,
            pose={"scale": s, "rotation": rot, "translation": t},
            n_iter=n_iter,
            timings=timings,
        )
