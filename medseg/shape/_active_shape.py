"""The active shape model (Cootes, Taylor, Cooper & Graham, 1995), in 3D.

Used twice: as the boundary refinement of :class:`medseg.segmenter.ShapePriorSegmenter`
(a search that starts from the landmarks the MRF chose) and as the standard baseline of the
evaluation (:mod:`medseg.evaluation.baselines.asm`, a search from the image centre, as a user of
ASM would start it).

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
   sigma that doubles per level, the profile step doubling with it; coarse to fine). Each
   iteration moves every landmark along its normal to the best-fitting profile position
   among ``2(m-k)+1`` offsets, then fits pose and shape parameters to the suggested points
   (similarity alignment, tangent projection, clamped parameters). A level ends when 90 %
   of the landmarks moved by at most one profile step, or after ``max_iter`` iterations.
   Every step is defined in physical space, so the search commutes with a similarity
   transform of the image and its start.

The point distribution model itself is :mod:`medseg.shape._point_distribution`; this module
(just over 400 lines) holds the profile models, the search and the model's file.

References
----------
T. F. Cootes, C. J. Taylor, D. H. Cooper, J. Graham, "Active shape models - their training
and application", Computer Vision and Image Understanding 61(1), 1995.
doi:10.1006/cviu.1995.1004

T. F. Cootes, C. J. Taylor, A. Lanitis, "Active shape models: evaluation of a
multi-resolution method for improving image search", BMVC 1994. doi:10.5244/C.8.32
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy.ndimage import gaussian_filter, map_coordinates
from sklearn.base import BaseEstimator
from sklearn.covariance import LedoitWolf
from tqdm.auto import tqdm

from medseg.errors import CohortError, ModelFileError, NotFittedError, ParameterError
from medseg.geometry import similarity_fit, vertex_normals
from medseg.io import check_format, load_arrays, physical_to_voxel, save_arrays, voxel_to_physical
from medseg.shape._point_distribution import landmark_mesh, point_distribution_model
from medseg.shape._prior import MIN_TRAINING_SHAPES

__all__ = [
    "ActiveShapeModel",
    "ShapeSearch",
]


# ----------------------------------------------------------------------------- profiles


def _pose(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale, rotation and translation of the similarity taking ``src`` onto ``dst``."""
    fit = similarity_fit(src, dst)
    return fit.scale, fit.rotation, fit.translation


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


@dataclass(frozen=True)
class ShapeSearch:
    """The result of :meth:`ActiveShapeModel.search`.

    Attributes
    ----------
    landmarks : (N, 3) float array, mm
    shape_parameters : (K,) float array
        Final mode weights ``b``.
    pose : dict
        ``scale`` (mm, centroid size), ``rotation`` (3, 3), ``translation`` (3,) mm.
    n_iter : list of int
        Iterations per searched level, coarse to fine.
    profile_cost : float
        How well the image fits the model at ``landmarks``: the mean Mahalanobis distance of
        the landmarks' grey-level profiles to their models at the finest level (lower is
        better; see :meth:`ActiveShapeModel.profile_cost`).
    """

    landmarks: np.ndarray
    shape_parameters: np.ndarray
    pose: dict
    n_iter: list
    profile_cost: float


_STATE_SCALARS = (
    "variance", "limit", "profile_half", "search_half", "step_mm", "n_levels", "max_iter",
)  # fmt: skip


class ActiveShapeModel(BaseEstimator):
    """Point distribution model, grey-level profile models and multi-resolution search.

    Parameters
    ----------
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
    closest_to_mean_ : int
        Index of the training shape nearest the mean after alignment (a template).
    profile_means_ : (levels, N, 2k+1) float array
    profile_precisions_ : (levels, N, 2k+1, 2k+1) float array
    training_costs_ : (S,) float array or None
        :meth:`profile_cost` of each training shape on its own image: how well a correct
        instance fits, the scale a search's cost is judged on. In-sample, so lower than a
        held-out case's at its truth, the more so the fewer the training shapes. None for a
        model saved before it existed (format version 1).
    """

    _converged_shift = 1  # profile steps; a level ends when 90 % of moves are this small

    def __init__(
        self,
        *,
        variance: float = 0.98,
        limit: float = 3.0,
        profile_half: int = 3,
        search_half: int = 6,
        step_mm: float = 1.0,
        n_levels: int = 3,
        max_iter: int = 20,
    ):
        self.variance = variance
        self.limit = limit
        self.profile_half = profile_half
        self.search_half = search_half
        self.step_mm = step_mm
        self.n_levels = n_levels
        self.max_iter = max_iter

    def _level_sigma_step(self, level: int) -> tuple[float, float]:
        step = self.step_mm * 2.0**level
        return 0.6 * step, step

    # -- training ---------------------------------------------------------------------------

    def fit(
        self, shapes, images: Sequence[sitk.Image], *, progress: bool = False
    ) -> ActiveShapeModel:
        """Learn the point distribution model and the profile models.

        Parameters
        ----------
        shapes : (S, N, 3) float array, mm
            Training landmarks in correspondence, each in its own image's physical space.
        images : sequence of S 3D SimpleITK images
        progress : bool, default False
        """
        if not 0.0 < self.variance <= 1.0:
            raise ParameterError("`variance` must be in (0, 1].")
        if self.search_half <= self.profile_half or self.profile_half < 1:
            raise ParameterError("need 1 <= `profile_half` < `search_half`.")
        if int(self.n_levels) < 1:
            raise ParameterError(f"`n_levels` must be >= 1, got {self.n_levels}")
        shapes = np.asarray(shapes, dtype=float)
        if shapes.ndim != 3 or shapes.shape[2] != 3:
            raise CohortError(f"training shapes must be (S, N, 3), got {shapes.shape}")
        if len(shapes) < MIN_TRAINING_SHAPES:
            raise CohortError(
                f"the ASM needs at least {MIN_TRAINING_SHAPES} training shapes, got {len(shapes)}"
            )
        if len(images) != len(shapes):
            raise CohortError(f"{len(shapes)} training shapes but {len(images)} images")
        pdm = point_distribution_model(shapes, variance=self.variance)
        self.mean_shape_ = pdm.mean
        self.modes_ = pdm.modes
        self.eigenvalues_ = pdm.eigenvalues
        self.mean_size_ = pdm.mean_size
        self.faces_ = landmark_mesh(pdm.mean)
        self.closest_to_mean_ = int(np.argmin(((pdm.aligned - pdm.mean) ** 2).sum(axis=(1, 2))))
        k = self.profile_half
        per_level: list[list[np.ndarray]] = [[] for _ in range(self.n_levels)]
        for i, image in enumerate(tqdm(images, desc="ASM profiles", disable=not progress)):
            normals = vertex_normals(shapes[i], self.faces_)
            for level in range(self.n_levels):
                sigma, step = self._level_sigma_step(level)
                arr = _smoothed(image, sigma)
                per_level[level].append(
                    _normalise(_profiles(image, arr, shapes[i], normals, k, step))
                )
        means, precisions = [], []
        for level in range(self.n_levels):
            g = np.stack(per_level[level], axis=1)  # (N, S, 2k+1)
            means.append(g.mean(axis=1))
            precisions.append(np.stack([LedoitWolf().fit(g_i).precision_ for g_i in g]))
        self.profile_means_ = np.stack(means)
        self.profile_precisions_ = np.stack(precisions)
        finest = per_level[0]  # (N, 2k+1) per training shape
        self.training_costs_ = np.array([self._cost(profiles) for profiles in finest])
        return self

    # -- search -----------------------------------------------------------------------------

    def _check_fitted(self) -> None:
        if not hasattr(self, "profile_means_"):
            raise NotFittedError("this ActiveShapeModel is not fitted yet: call fit(...)")

    def _instance(self, b: np.ndarray) -> np.ndarray:
        return self.mean_shape_ + np.tensordot(b, self.modes_, axes=1)

    def _fit_to_points(
        self, y: np.ndarray, b: np.ndarray
    ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """Pose and clamped shape parameters that best explain suggested points ``y``."""
        limits = self.limit * np.sqrt(self.eigenvalues_)
        for _ in range(5):
            s, rot, t = _pose(self._instance(b), y)
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
        s, rot, t = _pose(self._instance(b), y)
        return s, rot, t, b

    def search(self, image: sitk.Image, start=None, *, levels: int | None = None) -> ShapeSearch:
        """Fit the model to the image's boundary, from a start.

        Parameters
        ----------
        image : 3D SimpleITK image
        start : (N, 3) float array, mm, optional
            Landmarks to start from: the model instance (pose and shape parameters) closest
            to them starts the search. Default: the mean shape at the physical centre of the
            image, with unit pose (the mean training orientation and size).
        levels : int, optional
            Search only the finest ``levels`` resolution levels (a good start needs no
            coarse levels). Default: all.

        Returns
        -------
        ShapeSearch
        """
        self._check_fitted()
        b = np.zeros(len(self.eigenvalues_))
        if start is None:
            size_zyx = np.asarray(image.GetSize(), dtype=float)[::-1]
            centre = voxel_to_physical(image, ((size_zyx - 1.0) / 2.0)[None, :])[0]
            s, rot, t = self.mean_size_, np.eye(3), centre
        else:
            start = np.asarray(start, dtype=float)
            if start.shape != self.mean_shape_.shape:
                raise ParameterError(
                    f"`start` must be {self.mean_shape_.shape} landmarks, got {start.shape}"
                )
            if not np.ptp(start, axis=0).any():
                raise ParameterError("the `start` landmarks all coincide: no pose to start from")
            s, rot, t, b = self._fit_to_points(start, b)
        n_levels = self.n_levels if levels is None else min(int(levels), self.n_levels)
        if n_levels < 1:
            raise ParameterError(f"`levels` must be >= 1, got {levels}")
        k, m = self.profile_half, self.search_half
        shifts = np.arange(-(m - k), m - k + 1)
        n_iter = []
        for level in reversed(range(n_levels)):
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
        return ShapeSearch(
            landmarks=landmarks,
            shape_parameters=b,
            pose={"scale": s, "rotation": rot, "translation": t},
            n_iter=n_iter,
            profile_cost=self._profile_cost(image, arr, landmarks),
        )

    def _profile_cost(self, image: sitk.Image, finest: np.ndarray, landmarks) -> float:
        k = self.profile_half
        _, step = self._level_sigma_step(0)
        normals = vertex_normals(landmarks, self.faces_)
        return self._cost(_normalise(_profiles(image, finest, landmarks, normals, k, step)))

    def _cost(self, profiles: np.ndarray) -> float:
        """Mean Mahalanobis distance of (N, 2k+1) normalised finest-level profiles."""
        diff = profiles - self.profile_means_[0]
        return float(np.einsum("ni,nij,nj->n", diff, self.profile_precisions_[0], diff).mean())

    def profile_cost(self, image: sitk.Image, landmarks) -> float:
        """Mean Mahalanobis distance of the profiles at ``landmarks`` to the finest models.

        The model's own measure of how well an instance sits on the image's boundary,
        defined in physical space (pose invariant); the segmenter uses it to choose between
        refined MRF solutions.
        """
        self._check_fitted()
        landmarks = np.asarray(landmarks, dtype=float)
        if landmarks.shape != self.mean_shape_.shape:
            raise ParameterError(
                f"`landmarks` must be {self.mean_shape_.shape}, got {landmarks.shape}"
            )
        return self._profile_cost(image, _smoothed(image, self._level_sigma_step(0)[0]), landmarks)

    # -- persistence ------------------------------------------------------------------------

    FORMAT = "medseg.shape.ActiveShapeModel"
    # 2: the training shapes' own profile costs (training_costs); 1 still loads
    FORMAT_VERSION = 2

    def save(self, path) -> Path:
        """Write the fitted model to one ``.npz`` file (:func:`medseg.io.save_arrays`)."""
        self._check_fitted()
        arrays = {name: np.array(getattr(self, name)) for name in _STATE_SCALARS}
        arrays.update(
            mean_shape=self.mean_shape_,
            modes=self.modes_,
            eigenvalues=self.eigenvalues_,
            mean_size=np.array(self.mean_size_),
            faces=self.faces_,
            closest_to_mean=np.array(self.closest_to_mean_),
            profile_means=self.profile_means_,
            profile_precisions=self.profile_precisions_,
        )
        version = 1  # a model loaded from version 1 keeps it
        if self.training_costs_ is not None:
            arrays["training_costs"] = self.training_costs_
            version = self.FORMAT_VERSION
        header = {"format": self.FORMAT, "format_version": version}
        return save_arrays(path, arrays, header=header)

    @classmethod
    def load(cls, path) -> ActiveShapeModel:
        """Read a model written by :meth:`save` (or a model folder's headerless file of
        format version 3); ``ModelFileError`` if the file is not one."""
        header, state = load_arrays(path, what="active shape model")
        check_format(
            header, format=cls.FORMAT, version=cls.FORMAT_VERSION, source=str(path),
            missing_ok=True,
        )  # fmt: skip
        try:
            model = cls(
                variance=float(state["variance"]),
                limit=float(state["limit"]),
                profile_half=int(state["profile_half"]),
                search_half=int(state["search_half"]),
                step_mm=float(state["step_mm"]),
                n_levels=int(state["n_levels"]),
                max_iter=int(state["max_iter"]),
            )
            mean = np.asarray(state["mean_shape"], dtype=float)
            modes = np.asarray(state["modes"], dtype=float)
            eig = np.asarray(state["eigenvalues"], dtype=float)
            faces = np.asarray(state["faces"], dtype=np.int64)
            means = np.asarray(state["profile_means"], dtype=float)
            prec = np.asarray(state["profile_precisions"], dtype=float)
            mean_size = float(state["mean_size"])
            closest = int(state["closest_to_mean"])
            costs = state.get("training_costs")
            costs = None if costs is None else np.asarray(costs, dtype=float)
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{path} is incomplete or corrupt ({exc})") from None
        n, width = len(mean), 2 * model.profile_half + 1
        if (
            mean.shape != (n, 3)
            or modes.shape != (len(eig), n, 3)
            or faces.ndim != 2
            or faces.shape[1] != 3
            or faces.min(initial=0) < 0
            or faces.max(initial=0) >= n
            or means.shape != (model.n_levels, n, width)
            or prec.shape != (model.n_levels, n, width, width)
            or (costs is not None and (costs.ndim != 1 or not np.isfinite(costs).all()))
        ):
            raise ModelFileError(f"{path}: active shape model arrays of inconsistent shapes")
        model.mean_shape_, model.modes_, model.eigenvalues_ = mean, modes, eig
        model.mean_size_ = mean_size
        model.faces_ = faces
        model.closest_to_mean_ = closest
        model.profile_means_, model.profile_precisions_ = means, prec
        model.training_costs_ = costs
        return model
