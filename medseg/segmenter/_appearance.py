"""The image around the found shape, seen in the shape's frame, against the training images.

The MRF's prior is similarity invariant, and so are the detectors' features and the
handedness term under proper rotations. A configuration that is the right shape turned about
itself, onto the same surface (a near symmetry of the structure: on the phantom the bean
turned by 100-180 degrees, its landmarks within 1-2 mm of the surface and 12-20 mm from
their own sites), costs the prior nothing and finds candidates as good as the right one's.
What tells the two apart is the image around the structure: resampled into the frame of the
found landmarks (:class:`medseg.frame.ShapeFrame`), a correctly placed image looks like the
training images placed by their own landmarks, a turned one does not.

:class:`FrameAppearance` keeps the mean of the training images in the frame (each normalised
to zero mean and unit variance) and how well each training image correlates with the mean
of the others near the structure (within ``reach_mm`` of the reference landmarks: farther
out, a user's field of view, its padding or a turned crop's corners would decide, not the
anatomy). :meth:`FrameAppearance.score` is that correlation for found landmarks. When it
falls below what held-out training images reach, :meth:`FrameAppearance.search` registers
the image onto the mean over the frame's whole box (SimpleITK: a similarity transform,
correlation metric; the surroundings are what tell a turned shape from the right one) from
the found frame turned by each of the 60 rotations of the icosahedron about the reference
shape's principal axes (:func:`search_turns`), first on a smoothed coarse copy of the image,
and returns the reference shape carried through each of the few best registrations refined
to convergence on the image itself, and through the found frame refined alike: starts for
the active shape search. Of the shapes found from them, the segmenter judges the one that
correlates best near the structure, and keeps it when it correlates with the mean better,
over the box and near the structure, than the found landmarks and is them turned about
themselves (:meth:`FrameAppearance.prefers`). The starts come from the pose-free solution
and cover every rotation, so the check is pose free too.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from medseg.errors import ModelFileError, NotFittedError, ParameterError
from medseg.frame import ShapeFrame
from medseg.geometry import Similarity, principal_frame
from medseg.io import check_format, content_mask, load_arrays, resample_like, save_arrays
from medseg.threads import thread_map

__all__ = ["MIN_TURN_DEG", "FrameAppearance", "icosahedral_rotations", "search_turns"]

#: The check replaces the found landmarks only by a placement turned by at least this many
#: degrees from them. The configurations it is for, the shape turned about itself onto the
#: same surface, are 40-180 degrees off (phantom, kept fold models: the 12 replacements
#: turned by 41-176 degrees gained 0.09-0.91 Dice; the 8 turned by 5-28 degrees changed it
#: by -0.007 to +0.018). A search that ends near the found frame is a local correction,
#: which the coarse correlation judges less well than the detectors and the profile search
#: do (hippocampus: both replacements turned by 6 and 23 degrees lost Dice, 0.02 and 0.10).
MIN_TURN_DEG = 30.0

# Registration. The screen: every start on smoothed, coarse copies of the mean and the image
# (the Gaussian's sigma and the voxels 1.5 times the check's coarse spacing) until it nearly
# converges, its first step a coarse voxel; smoothed, the correlation's basin is wide, and
# coarse, an iteration is cheap. Then the few best, on the image itself, until they
# converge. Phantom (phantom_003 as acquired): ten screen iterations on the image itself
# left the truth's start, 38 degrees off, 27 off and 13th of 60; thirty on a coarse copy
# bring it within 17 degrees and first.
_SCREEN_ITERATIONS = 30
# 1.5: each screen registration 3.8 times cheaper than at 1 (the check's own grid). Phantom,
# 180 draws: losses against acquired 0.007 / 0.002 / 0.024 / 0.008 at 1 / 15 / 30 / 45
# degrees, one draw below Dice 0.5; at 1, 0.003 / -0.003 / 0.004 / -0.000 and none.
_SCREEN_COARSENING = 1.5
_SCREEN_SAMPLING = 0.2  # of the screen grid's voxels
_KEPT_STARTS = 6
_FINAL_ITERATIONS = 40
_SAMPLING = 0.3  # of the fixed grid's voxels, for the metric: 2.5 times faster, as accurate
_REACH_MARGIN = 1.25  # the image the registrations see: as far as the box reaches, and more
_MIN_BOX_VOXELS = 10  # fewer of the image's in the box: the box score takes the whole box


def icosahedral_rotations() -> np.ndarray:
    """The 60 proper rotations of the icosahedron, (60, 3, 3), the identity first.

    Every rotation is within 44 degrees of one of them; the cube's 24 leave gaps of 63
    degrees, farther than a registration comes in from (phantom_017 1 degree off its acquired
    pose: the truth's nearest cube start was 53 degrees off and ended 32 degrees off; the
    nearest of these, 20 degrees off, ended within 1.4 mm).
    """
    group = Rotation.create_group("I").as_matrix()
    first = int(np.argmin(np.linalg.norm(group - np.eye(3), axis=(1, 2))))
    return np.concatenate([group[first : first + 1], np.delete(group, first, axis=0)])


def search_turns(frame: ShapeFrame) -> np.ndarray:
    """The turns the search starts from, in the frame's coordinates, (60, 3, 3), the
    identity first: the icosahedron's rotations about the reference shape's principal axes.

    Among them are the half-turns about each of those axes, which carry an elongated shape
    onto its own surface: the turned copies the check is for are then one start away, not
    up to 44 degrees.
    """
    axes = principal_frame(frame.reference)[2]
    return axes @ icosahedral_rotations() @ axes.T


def _normalised(array: np.ndarray) -> np.ndarray:
    array = np.asarray(array, dtype=np.float64)
    return (array - array.mean()) / max(float(array.std()), 1e-12)


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two arrays of voxels."""
    return float(np.mean(_normalised(a) * _normalised(b)))


def _near(grid: ShapeFrame, reach_mm: float | None) -> np.ndarray:
    """The voxels of ``grid`` within ``reach_mm`` of a reference landmark (None: the larger
    of 4 mm and the landmarks' median spacing), (Z, Y, X) bool."""
    points = grid.reference
    if reach_mm is None:
        spacing = cKDTree(points).query(points, k=2)[0][:, 1]
        reach_mm = max(4.0, float(np.median(spacing)))
    image = grid.grid()
    size = image.GetSize()
    axes = [image.GetOrigin()[d] + image.GetSpacing()[d] * np.arange(size[d]) for d in range(3)]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    centres = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    near = cKDTree(points).query(centres, distance_upper_bound=float(reach_mm))[0] < np.inf
    return near.reshape(size).transpose(2, 1, 0)  # (x, y, z) -> (Z, Y, X)


class FrameAppearance:
    """The training images' mean in the shape's frame, and the check of found landmarks.

    The images are compared near the structure only (within ``reach_mm`` of the reference
    landmarks): farther out a user's field of view, its padding or a turned crop's corners
    would decide the correlation, not the anatomy.

    Parameters
    ----------
    spacing_ratio : float, default 2.0
        The grid's spacing as a multiple of the frame's: the check needs the structure's
        surroundings, not its detail.
    reach_mm : float or None, default None
        How far from the reference landmarks the images are compared; None: the larger of
        4 mm and the landmarks' median spacing.
    quantile : float, default 0.05
        :attr:`threshold_` is this quantile of the training images' held-out correlations.

    Attributes
    ----------
    mean_ : (Z, Y, X) float32 array
        The mean of the normalised training images on the frame's coarse grid.
    scores_ : (S,) float array
        Each training image's correlation with the mean of the others.
    threshold_ : float
        Below it, :meth:`ShapePriorSegmenter.segment` searches for a better placement.
    """

    FORMAT = "medseg.segmenter.FrameAppearance"
    FORMAT_VERSION = 1

    def __init__(
        self, *, spacing_ratio: float = 2.0, reach_mm: float | None = None, quantile: float = 0.05
    ):
        self.spacing_ratio = spacing_ratio
        self.reach_mm = reach_mm
        self.quantile = quantile

    def _grid(self, frame: ShapeFrame) -> ShapeFrame:
        return replace(frame, spacing=frame.spacing * float(self.spacing_ratio))

    def _upright(self, frame: ShapeFrame, image: sitk.Image, pose: Similarity) -> np.ndarray:
        """``image`` placed in the frame on the coarse grid, normalised."""
        return _normalised(sitk.GetArrayFromImage(self._grid(frame).resample(image, pose)))

    def _near(self, frame: ShapeFrame) -> np.ndarray:
        """:func:`_near` of the coarse grid, computed once per frame."""
        grid = self._grid(frame)
        key = (grid.spacing, grid.lower.tobytes(), grid.upper.tobytes(),
               grid.reference.tobytes(), self.reach_mm)  # fmt: skip
        cached = getattr(self, "_near_cache", None)
        if cached is None or cached[0] != key:
            self._near_cache = (key, _near(grid, self.reach_mm))
        return self._near_cache[1]

    def fit(self, frame: ShapeFrame, images, landmarks: ArrayLike) -> FrameAppearance:
        """Learn the mean from training images placed in ``frame`` by their ``landmarks``."""
        if not float(self.spacing_ratio) > 0:
            raise ParameterError(f"`spacing_ratio` must be > 0, got {self.spacing_ratio}")
        if not 0 <= float(self.quantile) <= 1:
            raise ParameterError(f"`quantile` must be in [0, 1], got {self.quantile}")
        landmarks = np.asarray(landmarks, dtype=float)
        if len(images) < 2 or len(images) != len(landmarks):
            raise ParameterError(
                f"FrameAppearance needs at least 2 images with landmarks each; got "
                f"{len(images)} images and {len(landmarks)} landmark sets"
            )
        stack = np.stack([
            self._upright(frame, image, frame.pose(points))
            for image, points in zip(images, landmarks, strict=True)
        ])  # fmt: skip
        near = self._near(frame)
        total = stack.sum(axis=0)
        n = len(stack)
        self.scores_ = np.array([
            _correlation(one[near], (total - one)[near] / (n - 1)) for one in stack
        ])  # fmt: skip
        self.mean_ = (total / n).astype(np.float32)
        self.threshold_ = float(np.quantile(self.scores_, float(self.quantile)))
        return self

    def fits(self, frame: ShapeFrame) -> bool:
        """Whether the fitted mean lies on ``frame``'s coarse grid."""
        return self.mean_.shape == tuple(self._grid(frame).grid().GetSize()[::-1])

    def _check_is_fitted(self, frame: ShapeFrame) -> None:
        if not hasattr(self, "mean_"):
            raise NotFittedError("this FrameAppearance is not fitted yet")
        if not self.fits(frame):
            raise ParameterError(
                f"the appearance mean has shape {self.mean_.shape}, not that of the frame's "
                "grid: it was fitted in another frame"
            )

    def scores(
        self, frame: ShapeFrame, image: sitk.Image, landmarks: ArrayLike
    ) -> tuple[float, float]:
        """The correlations of ``image`` placed by ``landmarks`` with the training mean, from
        one resampling: near the structure (what :attr:`threshold_` judges) and over the
        frame's box where the image shows something (what the registration of :meth:`search`
        maximises: neither the world beyond the image's field of view nor a constant
        padding of it, :func:`medseg.io.content_mask`)."""
        self._check_is_fitted(frame)
        pose = frame.pose(landmarks)
        upright = self._upright(frame, image, pose)
        region = self._near(frame)
        # the box as the registration sees it: the image's content only, not what lies
        # beyond its field of view nor a constant padding of it
        grid = self._grid(frame)
        content = sitk.GetArrayFromImage(grid.resample(content_mask(image), pose, is_label=True))
        box = content > 0 if np.count_nonzero(content) >= _MIN_BOX_VOXELS else slice(None)
        return (
            _correlation(upright[region], self.mean_[region]),
            _correlation(upright[box], self.mean_[box]),
        )

    def score(self, frame: ShapeFrame, image: sitk.Image, landmarks: ArrayLike) -> float:
        """The correlation near the structure (:meth:`scores`' first)."""
        self._check_is_fitted(frame)
        region = self._near(frame)
        upright = self._upright(frame, image, frame.pose(landmarks))
        return _correlation(upright[region], self.mean_[region])

    def prefers(
        self,
        frame: ShapeFrame,
        image: sitk.Image,
        found: ArrayLike,
        searched: ArrayLike,
        *,
        found_scores: tuple[float, float] | None = None,
    ) -> tuple[bool, dict]:
        """Whether the ``searched`` landmarks should replace the ``found`` ones in ``image``,
        and what decided it (``search_score``, ``search_box_score``, ``turn_deg``).

        They should when they correlate with the mean better both over the frame's box (what
        the search maximised) and near the shape (what :attr:`threshold_` judges), and are
        the shape turned by at least :data:`MIN_TURN_DEG` from the found one: a turned copy,
        which is what the check is for, not a local correction. ``found_scores``:
        :meth:`scores` of ``found``, when already known.
        """
        near_before, box_before = found_scores or self.scores(frame, image, found)
        near, box = self.scores(frame, image, searched)
        turn = frame.turn_deg(found, searched)
        better = box > box_before and near > near_before and turn >= MIN_TURN_DEG
        return better, {"search_score": near, "search_box_score": box, "turn_deg": turn}

    def search(
        self, frame: ShapeFrame, image: sitk.Image, landmarks: ArrayLike, *, n_jobs: int = 1
    ) -> np.ndarray:
        """The reference shape placed in ``image`` by registrations onto the mean, from the
        frame of ``landmarks`` turned by each of :func:`search_turns`: (K, N, 3) mm, one
        placement per registration refined to convergence, the one that correlates best near
        the structure (:meth:`score`) first.

        The registrations maximise the correlation over the frame's box: it leads them in
        from afar, but a placement turned from the truth can win it by a hair (phantom:
        0.613 against the truth's 0.607, and 0.65 near the structure against 0.92). So the
        few best of a screen are all refined and returned, to be told apart near the
        structure, where the threshold judges. The screen runs on copies of the image and
        the mean smoothed and resampled at 1.5 times the coarse grid's spacing: a wide
        basin, cheap iterations, so every start goes most of the way in.

        The found frame itself (the identity turn) is refined and returned too when the
        screen does not keep it: a turned placement must then beat the found one refined as
        it was, not the found landmarks as they are. On the phantom turned by 30 degrees
        (phantom_000, one draw) the screen ranked the found frame 10th of 60, its coarse copy
        drifting 28 degrees off; the six it kept were turned by 100-180 degrees, and the best
        of them (0.75 near the structure against the found landmarks' 0.58) replaced a right
        segmentation (Dice 0.88 -> 0.65). Refined on the image, the found frame reached 0.80.

        Every registration runs on one ITK thread (with more, the result moves in the
        seventh digit with their number: the same image gave another answer under
        ``medseg-segment --jobs 2`` than under ``--jobs 1``); the independent registrations
        run on ``n_jobs`` threads instead, in a fixed order, so the answer is the same on
        any number. A field of view padded with a constant (zeros, say) does not count: the
        metric sees only the image's content (:func:`medseg.io.content_mask`), as it sees
        nothing beyond an unpadded image's edge.
        """
        self._check_is_fitted(frame)
        grid = self._grid(frame)
        fixed = sitk.GetImageFromArray(self.mean_)
        fixed.CopyInformation(grid.grid())
        pose = frame.pose(landmarks)
        centre = frame.reference.mean(axis=0)
        # the image wherever a registration can take the frame's box: the box turned
        # about its centre, with room to move
        reach = np.linalg.norm(np.maximum(centre - frame.lower, frame.upper - centre))
        around = (pose.inverse(centre[None])[0], _REACH_MARGIN * reach / pose.scale)
        moving = _cropped(sitk.Cast(image, sitk.sitkFloat32), *around)
        mask = _padding_excluded(moving)
        # the screen's grid, coarser again, and the mean smoothed onto it
        screen = replace(grid, spacing=grid.spacing * _SCREEN_COARSENING).grid()
        spacing = screen.GetSpacing()[0]
        smooth_mean = sitk.SmoothingRecursiveGaussian(fixed, spacing)
        coarse_fixed = resample_like(smooth_mean, screen, is_label=False)
        step = spacing / pose.scale  # the screen grid's spacing, in image mm
        coarse, coarse_mask = _coarse(moving, mask, step)
        starts = [_frame_to_image(pose, turn, centre) for turn in search_turns(frame)]
        with _one_itk_thread():
            screened = thread_map(
                lambda start: _register(
                    coarse_fixed,
                    coarse,
                    coarse_mask,
                    start,
                    _SCREEN_ITERATIONS,
                    learning_rate=step,
                    sampling=_SCREEN_SAMPLING,
                ),
                starts,
                n_jobs,
            )
            order = sorted(range(len(starts)), key=lambda k: -screened[k][0])  # stable
            kept = [screened[k][1] for k in order[:_KEPT_STARTS]]
            if 0 not in order[:_KEPT_STARTS]:  # the found frame competes, refined alike
                kept.append(starts[0])
            final = thread_map(
                lambda start: _register(fixed, moving, mask, start, _FINAL_ITERATIONS),
                kept,
                n_jobs,
            )
        placed = np.stack([
            [transform.TransformPoint(p) for p in frame.reference.tolist()]
            for _, transform in final
        ])  # fmt: skip
        near = np.array([self.score(frame, image, points) for points in placed])
        return placed[np.argsort(-near, kind="stable")]

    # -- persistence ------------------------------------------------------------------------

    def save(self, path) -> Path:
        """Write the fitted check to one ``.npz`` file."""
        arrays = {
            "mean": self.mean_,
            "scores": self.scores_,
            "threshold": np.array(self.threshold_),
            "spacing_ratio": np.array(float(self.spacing_ratio)),
            "reach_mm": np.array(np.nan if self.reach_mm is None else float(self.reach_mm)),
            "quantile": np.array(float(self.quantile)),
        }
        header = {"format": self.FORMAT, "format_version": self.FORMAT_VERSION}
        return save_arrays(path, arrays, header=header)

    @classmethod
    def load(cls, path) -> FrameAppearance:
        """Read a check written by :meth:`save`; ``ModelFileError`` if the file is not one."""
        header, arrays = load_arrays(path, what="frame appearance")
        check_format(header, format=cls.FORMAT, version=cls.FORMAT_VERSION, source=str(path))
        try:
            reach = float(arrays["reach_mm"])
            model = cls(
                spacing_ratio=float(arrays["spacing_ratio"]),
                reach_mm=None if np.isnan(reach) else reach,
                quantile=float(arrays["quantile"]),
            )
            model.mean_ = np.asarray(arrays["mean"], dtype=np.float32)
            model.scores_ = np.asarray(arrays["scores"], dtype=float)
            model.threshold_ = float(arrays["threshold"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{path} is incomplete or corrupt ({exc})") from None
        if model.mean_.ndim != 3 or not np.isfinite(model.mean_).all():
            raise ModelFileError(f"{path}: the appearance mean is not a finite 3D array")
        return model


def _frame_to_image(pose: Similarity, turn: np.ndarray, centre: np.ndarray):
    """The transform from frame mm to image mm of ``pose`` turned by ``turn`` about
    ``centre`` (SimpleITK's fixed-to-moving direction)."""
    matrix = pose.rotation.T @ turn.T  # frame -> image, without the scale
    transform = sitk.Similarity3DTransform()
    transform.SetCenter(centre.tolist())
    transform.SetMatrix(matrix.ravel().tolist())
    transform.SetScale(1.0 / pose.scale)
    transform.SetTranslation((pose.inverse(centre[None])[0] - centre).tolist())
    return transform


@contextmanager
def _one_itk_thread():
    """ITK's filters on one thread while inside (its default is a process-wide setting)."""
    before = sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
    try:
        yield
    finally:
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(before)


def _padding_excluded(image: sitk.Image) -> sitk.Image | None:
    """:func:`content_mask` of ``image`` when it leaves out some voxels and keeps some;
    None (no mask) otherwise."""
    mask = content_mask(image)
    kept = int(np.count_nonzero(sitk.GetArrayViewFromImage(mask)))
    return mask if 0 < kept < mask.GetNumberOfPixels() else None


def _cropped(image: sitk.Image, centre: np.ndarray, radius: float) -> sitk.Image:
    """The part of ``image`` within the box of a ball (``centre``, ``radius``: mm): the
    registrations see nothing farther, and their metric's gradient image is computed over
    the moving image's every voxel."""
    index = np.asarray(image.TransformPhysicalPointToContinuousIndex(centre.tolist()))
    half = radius / np.asarray(image.GetSpacing())
    size = np.asarray(image.GetSize())
    low = np.clip(np.floor(index - half), 0, size - 1).astype(int)
    high = np.clip(np.ceil(index + half) + 1, low + 1, size).astype(int)
    if np.all(low == 0) and np.all(high == size):
        return image
    return sitk.RegionOfInterest(image, (high - low).tolist(), low.tolist())


def _coarse(image: sitk.Image, mask, step: float):
    """``image`` smoothed by a Gaussian of ``step`` mm and resampled at ``step`` mm (never
    finer than it is), with ``mask`` (or None) on the same grid: what the screen registers.

    With a mask, the image is smoothed over the mask's voxels alone (a normalised
    convolution), so that a padding does not bleed into the content near its edge, and the
    coarse mask keeps the voxels whose Gaussian lies mostly in the content."""
    spacing = np.maximum(np.asarray(image.GetSpacing()), step)
    size = np.maximum(np.round(np.asarray(image.GetSize()) * image.GetSpacing() / spacing), 2)
    grid = sitk.Image([int(n) for n in size], sitk.sitkUInt8)
    grid.SetSpacing(spacing.tolist())
    grid.SetDirection(image.GetDirection())
    first = np.asarray(image.GetOrigin()) + np.asarray(image.GetDirection()).reshape(3, 3) @ (
        0.5 * (spacing - np.asarray(image.GetSpacing()))
    )
    grid.SetOrigin(first.tolist())

    def coarse(values: sitk.Image) -> sitk.Image:
        if min(values.GetSize()) >= 4:  # ITK's recursive Gaussian needs 4 voxels a side
            values = sitk.SmoothingRecursiveGaussian(values, float(step))
        return resample_like(values, grid, is_label=False)

    image = sitk.Cast(image, sitk.sitkFloat32)  # the fixed mean's type: ITK wants one
    if mask is None:
        return coarse(image), None
    inside = sitk.Cast(mask > 0, sitk.sitkFloat32)
    weight = sitk.GetArrayFromImage(coarse(inside))
    total = sitk.GetArrayFromImage(coarse(image * inside))
    # a mean over the content where the Gaussian holds enough of it (every neighbour of a
    # kept voxel, for the interpolation), else nothing
    values = np.where(weight > 0.1, total / np.maximum(weight, 0.1), 0.0).astype(np.float32)
    values = sitk.GetImageFromArray(values)
    values.CopyInformation(grid)
    kept = weight > 0.5
    if not kept.any():
        return values, None
    mask = sitk.GetImageFromArray(kept.astype(np.uint8))
    mask.CopyInformation(grid)
    return values, mask


def _register(
    fixed,
    moving,
    mask,
    start,
    iterations: int,
    *,
    learning_rate: float = 1.0,
    sampling: float = _SAMPLING,
):
    """(correlation, transform) of a registration from ``start`` (not modified), the metric
    on the voxels of ``mask`` (None: all) of ``moving``."""
    transform = sitk.Similarity3DTransform(start)
    method = sitk.ImageRegistrationMethod()
    method.SetMetricAsCorrelation()
    if mask is not None:
        method.SetMetricMovingMask(mask)
    method.SetNumberOfThreads(1)  # ITK's threads add the metric in their own order
    if sampling < 1.0:  # a fixed seed: the same samples, the same registration, every run
        method.SetMetricSamplingStrategy(method.REGULAR)
        method.SetMetricSamplingPercentage(float(sampling), 1)
    method.SetInterpolator(sitk.sitkLinear)
    method.SetOptimizerAsRegularStepGradientDescent(
        learningRate=float(learning_rate), minStep=1e-3, numberOfIterations=int(iterations)
    )
    method.SetOptimizerScalesFromPhysicalShift()
    method.SetInitialTransform(transform, inPlace=True)
    try:
        method.Execute(fixed, moving)
    except RuntimeError:  # the moving image left the fixed grid: no overlap to measure
        return -np.inf, transform
    return -float(method.GetMetricValue()), transform
