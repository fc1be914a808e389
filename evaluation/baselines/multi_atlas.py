"""Multi-atlas registration with majority voting: the classical baseline of atlas segmentation.

Each of a few training cases (the *atlases*: an image and the binary mask of the structure)
is registered to the test image with SimpleITK's registration framework: a moments
initialisation (:func:`SimpleITK.CenteredTransformInitializer`, ``MOMENTS``: the centres of
intensity mass aligned), then an affine transform optimised for Mattes mutual information,
coarse to fine (shrink factors 4, 2, 1 with Gaussian smoothing), linear interpolation of the
moving image, regular-step gradient descent with parameter scales from physical shifts.
Every atlas label map is resampled with nearest neighbour onto the test image's grid; a
voxel is inside the structure where a strict majority of the atlases say so, and takes the
sub-label (hippocampus: 1 anterior, 2 posterior) most of them give it (ties: the smaller
value). A single label gives a binary mask, as does every structure without sub-labels.

Nothing in it is invariant to pose: the moments initialisation removes a translation only,
and the affine optimisation is local, so large rotations are its weakness (what the
perturbation study measures). It predicts no landmarks (``landmarks`` is None; the
evaluation records NaN landmark errors).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from numbers import Integral, Real

import numpy as np
import SimpleITK as sitk
from sklearn.base import BaseEstimator
from sklearn.utils import check_random_state

from medseg.errors import CohortError, NotFittedError, ParameterError
from medseg.io import label_values, read_image, select_labels

__all__ = ["MultiAtlasBaseline", "MultiAtlasResult", "SELECTIONS"]

#: How :meth:`MultiAtlasBaseline.fit` picks its atlases: the training cases whose field of
#: view (mm) is closest to the cohort's median ("size", deterministic), or at random.
SELECTIONS = ("size", "random")


@dataclass
class MultiAtlasResult:
    """The result of :meth:`MultiAtlasBaseline.segment`.

    Attributes
    ----------
    label : SimpleITK image, uint8
        Majority vote of the registered atlas label maps, on the input image's grid exactly:
        the training labels' values when there are several, else 1.
    votes : (z, y, x) int array
        How many atlases put each voxel inside the structure (any of its labels).
    transforms : list of SimpleITK transforms
        Per atlas, the affine transform found (maps points of the input image into the
        atlas image), in the order of ``atlases_``.
    landmarks : None
        No landmarks (present so that evaluation code treats every method alike).
    mrf : None
    timings : dict
        ``registration`` and ``voting`` seconds.
    """

    label: sitk.Image
    votes: np.ndarray
    transforms: list
    landmarks: None = None
    mrf: None = None
    timings: dict = field(default_factory=dict)


def _physical_extent(image: sitk.Image) -> np.ndarray:
    return np.asarray(image.GetSize(), dtype=float) * np.asarray(image.GetSpacing())


class MultiAtlasBaseline(BaseEstimator):
    """Affine multi-atlas registration (Mattes MI) and majority voting.

    Parameters
    ----------
    labels : tuple of int, default (1,)
        Labels of the training label maps forming the structure (their union).
    n_atlases : int, default 9
        Training cases kept as atlases (all of them if the cohort is smaller).
    selection : {"size", "random"}, default "size"
        "size": the cases whose field of view in mm is closest to the cohort's median
        (ties in cohort order; no randomness); "random": drawn with ``random_state``.
    shrink_factors : sequence of int, default (4, 2, 1)
        Resolution levels of the registration, coarse to fine.
    smoothing_sigmas : sequence of float, default (2, 1, 0)
        Gaussian smoothing per level, in mm.
    n_iterations : int, default 100
        Optimiser iterations per level at most.
    learning_rate : float, default 1.0
        Initial step of the regular-step gradient descent (in units of the physical-shift
        scales, about mm).
    sampling_percentage : float, default 0.2
        Fraction of the voxels sampled (at random, seeded) for the metric.
    n_histogram_bins : int, default 32
        Bins of the Mattes mutual information.
    n_threads : int, default 1
        ITK threads per registration, fixed so that the result does not depend on the
        machine.
    random_state : int, RandomState or None
        Seeds the metric's sampling (and the atlas draw with ``selection="random"``): the
        same value gives the same labels.
    n_jobs : int, default 1
        Atlases registered at once (threads; SimpleITK releases the GIL).

    Attributes
    ----------
    atlases_ : list of str
        Case ids of the atlases.
    atlas_images_ : list of SimpleITK images (float32)
    atlas_masks_ : list of SimpleITK images (uint8: the label values kept, or 0/1 for one label)
    seed_ : int
        Base seed of the registrations (atlas ``k`` uses ``seed_ + k``).
    """

    def __init__(
        self,
        labels: Sequence[int] = (1,),
        n_atlases: int = 9,
        *,
        selection: str = "size",
        shrink_factors: Sequence[int] = (4, 2, 1),
        smoothing_sigmas: Sequence[float] = (2.0, 1.0, 0.0),
        n_iterations: int = 100,
        learning_rate: float = 1.0,
        sampling_percentage: float = 0.2,
        n_histogram_bins: int = 32,
        n_threads: int = 1,
        random_state=None,
        n_jobs: int = 1,
    ):
        self.labels = labels
        self.n_atlases = n_atlases
        self.selection = selection
        self.shrink_factors = shrink_factors
        self.smoothing_sigmas = smoothing_sigmas
        self.n_iterations = n_iterations
        self.learning_rate = learning_rate
        self.sampling_percentage = sampling_percentage
        self.n_histogram_bins = n_histogram_bins
        self.n_threads = n_threads
        self.random_state = random_state
        self.n_jobs = n_jobs

    # ------------------------------------------------------------------------- checks

    def _check_params(self) -> None:
        def positive_int(name: str, minimum: int = 1) -> None:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, Integral) or value < minimum:
                raise ParameterError(f"`{name}` must be an integer >= {minimum}, got {value!r}")

        for name in ("n_atlases", "n_iterations", "n_threads", "n_jobs"):
            positive_int(name)
        positive_int("n_histogram_bins", 2)
        if self.selection not in SELECTIONS:
            raise ParameterError(f"`selection` must be one of {SELECTIONS}, got {self.selection!r}")
        labels = np.atleast_1d(np.asarray(self.labels))
        if not labels.size or not np.issubdtype(labels.dtype, np.integer):
            raise ParameterError(f"`labels` must be integers, got {self.labels!r}")
        shrink, sigmas = list(self.shrink_factors), list(self.smoothing_sigmas)
        if not shrink or len(shrink) != len(sigmas):
            raise ParameterError(
                "`shrink_factors` and `smoothing_sigmas` must be non-empty and of the same "
                f"length (one per level), got {shrink} and {sigmas}"
            )
        if any(isinstance(f, bool) or not isinstance(f, Integral) or f < 1 for f in shrink):
            raise ParameterError(f"`shrink_factors` must be integers >= 1, got {shrink}")
        if any(not isinstance(s, Real) or not 0 <= s < np.inf for s in sigmas):
            raise ParameterError(f"`smoothing_sigmas` must be finite and >= 0, got {sigmas}")
        if not isinstance(self.learning_rate, Real) or not 0 < self.learning_rate < np.inf:
            raise ParameterError(f"`learning_rate` must be > 0, got {self.learning_rate!r}")
        pct = self.sampling_percentage
        if not isinstance(pct, Real) or not 0 < pct <= 1:
            raise ParameterError(f"`sampling_percentage` must be in (0, 1], got {pct!r}")

    # ------------------------------------------------------------------------- fit

    def fit(self, cohort) -> MultiAtlasBaseline:
        """Choose the atlases and keep their images and masks.

        Parameters
        ----------
        cohort : Cohort
            Training cases with images and label maps.

        Raises
        ------
        ParameterError
            A parameter value that cannot be used.
        CohortError
            An empty cohort.
        LabelError
            An atlas whose label map has none of ``labels``.
        """
        self._check_params()
        if len(cohort) == 0:
            raise CohortError("the multi-atlas baseline needs at least one training case")
        rng = check_random_state(self.random_state)
        n = min(int(self.n_atlases), len(cohort))
        if self.selection == "random":
            chosen = sorted(rng.choice(len(cohort), size=n, replace=False).tolist())
            images = [read_image(cohort[i].load_image()) for i in chosen]
        else:
            all_images = [read_image(case.load_image()) for case in cohort]
            extents = np.stack([_physical_extent(im) for im in all_images])
            distance = np.linalg.norm(extents - np.median(extents, axis=0), axis=1)
            chosen = sorted(np.argsort(distance, kind="stable")[:n].tolist())
            images = [all_images[i] for i in chosen]
        labels = tuple(int(v) for v in np.atleast_1d(self.labels))
        self.atlases_ = [cohort[i].case_id for i in chosen]
        self.atlas_images_ = [sitk.Cast(im, sitk.sitkFloat32) for im in images]
        self.atlas_masks_ = []
        for i in chosen:
            label_map = cohort[i].load_label()
            select_labels(label_map, labels, name=f"label map of {cohort[i].case_id}")  # not empty
            self.atlas_masks_.append(label_values(label_map, labels))
        # sitk's seed 0 means "the wall clock": draw from [1, 2**31 - n].
        self.seed_ = int(rng.randint(1, 2**31 - 1 - n))
        return self

    # ------------------------------------------------------------------------- segment

    def _register(self, fixed: sitk.Image, k: int) -> sitk.Transform:
        moving = self.atlas_images_[k]
        initial = sitk.CenteredTransformInitializer(
            fixed,
            moving,
            sitk.AffineTransform(fixed.GetDimension()),
            sitk.CenteredTransformInitializerFilter.MOMENTS,
        )
        method = sitk.ImageRegistrationMethod()
        method.SetMetricAsMattesMutualInformation(numberOfHistogramBins=int(self.n_histogram_bins))
        method.SetMetricSamplingStrategy(method.RANDOM)
        method.SetMetricSamplingPercentage(float(self.sampling_percentage), self.seed_ + k)
        method.SetInterpolator(sitk.sitkLinear)
        method.SetOptimizerAsRegularStepGradientDescent(
            learningRate=float(self.learning_rate),
            minStep=1e-3,
            numberOfIterations=int(self.n_iterations),
            relaxationFactor=0.5,
            gradientMagnitudeTolerance=1e-6,
        )
        method.SetOptimizerScalesFromPhysicalShift()
        method.SetShrinkFactorsPerLevel([int(f) for f in self.shrink_factors])
        method.SetSmoothingSigmasPerLevel([float(s) for s in self.smoothing_sigmas])
        method.SmoothingSigmasAreSpecifiedInPhysicalUnitsOn()
        method.SetInitialTransform(initial, inPlace=False)
        method.SetNumberOfThreads(int(self.n_threads))
        return method.Execute(fixed, moving)

    def segment(self, image, **_ignored) -> MultiAtlasResult:
        """Register every atlas to ``image`` and take the majority vote of their masks.

        Parameters
        ----------
        image : 3D SimpleITK image, nibabel image or path

        Returns
        -------
        MultiAtlasResult
            ``label`` on the input's grid (size, spacing, origin, direction).
        """
        if not hasattr(self, "atlas_images_"):
            raise NotFittedError("this MultiAtlasBaseline is not fitted yet: call fit(cohort)")
        t0 = time.perf_counter()
        target = read_image(image)
        fixed = sitk.Cast(target, sitk.sitkFloat32)
        atlases = range(len(self.atlas_images_))
        if self.n_jobs == 1:
            transforms = [self._register(fixed, k) for k in atlases]
        else:
            from joblib import Parallel, delayed

            # each thread gets its own copy of the target: ITK filters update their inputs'
            # pipeline state, which concurrent registrations must not share
            voxels = sitk.GetArrayFromImage(fixed)
            copies = [sitk.GetImageFromArray(voxels) for _ in atlases]
            for copy in copies:
                copy.CopyInformation(fixed)
            transforms = Parallel(n_jobs=self.n_jobs, prefer="threads")(
                delayed(self._register)(copy, k) for copy, k in zip(copies, atlases, strict=True)
            )
        timings = {"registration": time.perf_counter() - t0}
        t0 = time.perf_counter()
        values = sorted({int(v) for v in np.atleast_1d(self.labels)})
        values = values if len(values) > 1 else [1]  # a single label is stored as 1
        shape = sitk.GetArrayViewFromImage(fixed).shape
        per_value = np.zeros((len(values),) + shape, dtype=np.int32)
        for mask, transform in zip(self.atlas_masks_, transforms, strict=True):
            warped = sitk.GetArrayFromImage(  # a copy: a view would outlive its image
                sitk.Resample(mask, target, transform, sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)
            )
            for j, v in enumerate(values):
                per_value[j] += warped == v
        votes = per_value.sum(axis=0)
        inside = 2 * votes > len(transforms)
        winner = np.asarray(values, dtype=np.uint8)[np.argmax(per_value, axis=0)]
        label = sitk.GetImageFromArray(np.where(inside, winner, 0).astype(np.uint8))
        label.CopyInformation(target)
        timings["voting"] = time.perf_counter() - t0
        return MultiAtlasResult(label=label, votes=votes, transforms=transforms, timings=timings)
