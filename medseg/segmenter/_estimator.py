"""The segmenter: landmarks + Random-Forest detectors + triplet shape prior + MRF + TPS.

:class:`ShapePriorSegmenter` composes the parts of the package and nothing else: the
correspondence step, the detectors, the prior, the solver and the reconstruction know only
plain arrays and images, and this module is the one place that wires them together. It
is longer than the project's other modules because the class docstring documents every
parameter with what it measured; the logic is ``fit`` and ``segment``.

References
----------
C. Wang, O. Teboul, F. Michel, S. Essafi, N. Paragios, "3D knowledge-based segmentation
using pose-invariant higher-order graphs", MICCAI 2010. doi:10.1007/978-3-642-15711-0_24
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from sklearn.base import BaseEstimator
from sklearn.utils import check_random_state
from tqdm.auto import tqdm

from medseg.correspondence import cohort_landmarks, label_surface, landmarks_from_labels
from medseg.datasets import Cohort
from medseg.detection import CandidateSet, LandmarkDetector, gradient_directions
from medseg.errors import CohortError, NotFittedError, ParameterError
from medseg.frame import ShapeFrame
from medseg.geometry import procrustes_disparity
from medseg.io import as_input_type, label_values, read_image, select_labels
from medseg.memory import memory_limit_bytes
from medseg.mrf import DEFAULT_MAX_BYTES, MRF, solve
from medseg.reconstruction import warp_labels, warp_surface
from medseg.segmenter import _memory, _persistence
from medseg.segmenter._appearance import FrameAppearance
from medseg.segmenter._boundary import BoundaryStage
from medseg.segmenter._frame_pass import in_frame_passes
from medseg.segmenter._hypotheses import (
    check_not_collapsed,
    collapsed,
    margin,
    refined_hypotheses,
)
from medseg.segmenter._result import Hypothesis, Located, Segmentation
from medseg.shape import ActiveShapeModel, OrientationPrior, TripletPrior

__all__ = ["ShapePriorSegmenter", "load_model", "MIN_TRAINING_CASES", "QUALITY_THRESHOLD"]

#: Fewest training cases a model (and a cross-validation fold) may have.
MIN_TRAINING_CASES = 5
#: ``Segmentation.quality["score"]`` above which a segmentation is flagged as likely wrong:
#: its disagreement between image and shape is this many standard deviations beyond what
#: held-out training cases showed.
QUALITY_THRESHOLD = 3.0
_SHAPE_MODEL_LEVELS = 3  # resolution levels the refining active shape model learns
# trees of a voxel forest of the regional stage per landmark-forest tree: 15 at the defaults.
# benchmarks/bench_voxel_classifier.py (2026-12-03, 100 hippocampus cases, 20 of other
# subjects): 15 trees instead of 30 fit in 38 s instead of 68 and predict in 49 ms a case
# instead of 82, for a Dice after the cut 0.001 lower (paired s.e. 0.0008)
_BOUNDARY_TREES = 0.75


class ShapePriorSegmenter(BaseEstimator):
    """Knowledge-based segmentation with a pose-invariant higher-order shape prior.

    Parameters
    ----------
    n_landmarks : int or None, default None
        Landmarks per shape; None sizes it to the structure (see
        :func:`medseg.correspondence.landmarks_from_labels`).
    labels : tuple of int, default (1,)
        Labels of the training label maps that form the structure (their union).
    n_candidates : int, default 15
        Candidates per landmark (L). Measured against 20 (2026-12-04,
        ``benchmarks/bench_settings.py``): hippocampus Dice +0.0002 (paired s.e. 0.0020, 61
        cases of 40 held-out subjects) at 0.73 times the time a case; phantom 5-fold Dice
        +0.015 (s.e. 0.030, 60 cases over 3 seeds), landmark error 6.4 -> 5.5 mm. 12 starts
        to lose (hippocampus -0.003). The MRF's tables grow as L cubed.
    cliques : {"knn", "delaunay", "all"}, default "knn"
        Triplet cliques of the prior.
    density : {"gmm", "gaussian", "parzen"}, default "gmm"
        Density of the triplet invariant per clique.
    invariant : {"distance_size", "distance", "angle"}, default "distance_size"
        Triplet invariant of the prior (see :class:`medseg.shape.TripletPrior`): the paper's
        relative distances (``"distance"``, blind to scale), or with the log perimeter of the
        triangle (``"distance_size"``): invariant to rotation and translation and to the
        scales of the training population; with it the MRF stops matching look-alike
        triples of the wrong size among the candidates.
    alpha : float, default 1.0
        Weight of the prior against the detectors' evidence.
    orientation_weight : float, default 1.0
        Weight of the handedness term (:class:`medseg.shape.OrientationPrior`) added to the
        triplet potentials: the side of each clique's triangle the image gradient points to,
        which rotation cannot change but a mirror-image labelling reverses. The relative
        distances are blind to reflection, so without it (0, the paper's prior) a nearly
        symmetric structure's mirrored labelling costs the same as the right one.
    orientation_sigma_mm : float, default 1.0
        Scale (mm) of the Gaussian derivative giving the boundary directions.
    refine_levels : int, default 2
        Resolution levels (finest first, at most 3) of the active-shape search
        (:class:`medseg.shape.ActiveShapeModel`) that starts from the MRF's landmarks: the
        point distribution model is fitted to them and moved onto the boundary's grey-level
        profiles, so the result is no longer tied to the candidates' grid and to their
        localisation noise. 0 keeps the MRF's landmarks, as in the paper.
    n_hypotheses : int, default 4
        MRF solutions refined per image (with ``refine_levels > 0``): after the optimum,
        each further solve makes the candidates near the earlier solutions' landmarks cost
        more, and the refined solution whose boundary profiles fit the image best is kept
        (a pose-invariant check of the MRF's choice by the image). 1 refines the optimum
        only. On the phantom (5-fold) the mean landmark error was 8.3, 6.6, 5.6, 5.0 and
        5.4 mm with 1 to 5; on hippocampus the Dice did not change; each costs one MRF
        solve and one search (4 take 1.6 times the CPU time of 2).
    hypothesis_quantile : float or None, default 0.9
        The further hypotheses are solved only when the refined optimum fits the image
        worse (a higher profile cost) than this quantile of the training shapes' fits on
        their own images (``shape_model_.training_costs_``): an optimum that fits as well
        as most training shapes is kept alone. None always solves ``n_hypotheses`` (as do
        models saved before format version 6). Hippocampus, 5-fold by subject, the 199
        cases, kept fold models: 27 cases needed the further solves as acquired, 28 under
        the random similarity; Dice against always solving +0.0001 (s.e. 0.0005) and
        +0.0003 (s.e. 0.0004); on 61 held-out cases a case took 0.81 times as long
        (median 1.71 s against 2.07, one thread). With 1 hypothesis for every case the
        Dice fell 0.0011 (s.e. 0.0011). On the phantom the held-out fits stay above the
        training shapes' (16 training shapes fit their own images closely), so every case
        is solved further as before (its 5-fold figures unchanged to the bit).
    frame_passes : int, default 0
        Passes of the whole inference (detection, MRF, refinement) in the shape's own frame
        (:class:`medseg.frame.ShapeFrame`) after the first one in the image as given: the
        image resampled so that the landmarks found last sit on the reference shape,
        upright, at its mean size, in a training-like field of view. The frame comes from
        the pose-free solution, so the result stays pose free while the detectors and the
        search see the structure as in training. 0 is the paper's single pass.
    appearance_check : bool, default True
        After the refinement, compare the image near the found landmarks, seen in the
        shape's frame, with the training images seen in theirs
        (:class:`~medseg.segmenter.FrameAppearance`): below what held-out training images
        reach (its 5 % quantile), register the image onto their mean from the found frame
        turned every way, refine the reference shape carried through the best registration,
        and keep it when it correlates better with the mean, over the frame's box and near
        the shape, and is the found shape turned by at least 30 degrees. The
        similarity-invariant prior cannot tell the shape from the shape turned about itself
        onto the same surface (on the phantom the cause of most failures); the image around
        it can. A search that ends close to the found frame is left to the detectors and the
        profile search: on the hippocampus the two it replaced, turned by 6 and 23 degrees,
        lost Dice. A searched case costs 1-6 s. Models of format versions 1-6 have no check.
    boundary : bool, default True
        The regional stage (:class:`~medseg.segmenter.BoundaryStage`): in the shape's
        frame, a voxel classifier and a graph cut move the warped template's boundary (and
        its sub-labels) onto the image's evidence. False at :meth:`fit` trains without it;
        False at :meth:`segment` returns the shape-only label map (as does a model saved
        before the stage existed, format versions 1-4).
    landmark_noise_mm : float, default 1.5
        Standard deviation of the localisation noise of detected landmarks. The clique
        densities are fitted to training shapes jittered by this much (``n_noise_copies``
        copies each), so that they model where *detected* landmarks fall, not only the exact
        training positions; 0 fits the exact shapes (then any real configuration gets
        potentials in the thousands and the detectors' evidence is drowned).
    n_noise_copies : int, default 10
        Jittered copies of each training shape for the clique densities.
    n_estimators : int, default 20
        Trees per landmark forest. 20 trees lose nothing against 60 (hippocampus, 80
        training cases, 20 held-out subjects, max_iter 100: mean Dice 0.815 with 20, 0.817
        with 30, 0.812 with 60, the paired differences within one standard error) and take
        a third of the time to train, store and evaluate. 10 trees were tried and left
        out (2026-12-07): on the hippocampus (138-case model, 61 held-out cases of 40
        subjects, retrained) they held the Dice (0.879 -> 0.882, paired s.e. 0.004) for
        detection 0.69 -> 0.43 s a case, training 674 -> 468 s and a model of 5.6 MB
        instead of 11; but on the phantom's pose bench (``bench_phantom_pose.py``, 180
        draws) 17 draws flipped, 3 of them to Dice 0.32-0.48, and the losses against the
        acquired cases went from 0.003 / 0.004 / 0.013 / 0.016 to 0.000 / 0.023 / 0.039 /
        0.009 at 1 / 15 / 30 / 45 degrees. The regional stage's voxel
        forests get 0.75 times as many (15 at the default: against 30, the Dice after its
        cut 0.001 lower, within the paired standard error, for half the fitting; 60 with
        twice the training voxels gave 0.862 against 0.860 for three times the training).
    augment_poses : int, default 2
        Copies of every training image in a random pose, size and field of view that the
        detectors also learn from (:class:`~medseg.detection.LandmarkDetector`,
        ``augment_poses``): without them the forests learn the crops' field of view and
        lose most landmarks under padding, rotation or scaling. About 3 times the detector
        training; 0 trains on the images as they are.
    smoothing : float, default 0.0
        Thin-plate spline smoothing of the reconstruction.
    max_iter : int, default 100
        Iterations of the MRF solver (its first solve; the further hypotheses take at most
        30, warm-started). 100 rather than 300: a third of the time, and on the hippocampus
        (80 training cases, 20 held-out subjects) a mean Dice 0.007 lower (0.812 against
        0.819, within one standard error of the paired differences). Fewer was tried and
        not taken (2026-12-06, the five fold models of the 5-fold run, every one of the 199
        cases segmented as acquired and under a random similarity): 60, with the further
        hypotheses at 15 instead of 30, took 0.91 of a case's time (8 cases, one process,
        the two settings alternated) for a Dice 0.0014 lower (paired s.e. 0.0011 over the
        398 segmentations).
    mrf_method : {"mplp", "srmp", "subgradient"}, default "mplp"
        MRF solver (see :func:`medseg.mrf.solve`); "subgradient" is the paper's dual
        decomposition into factor trees.
    random_state : int, Generator, RandomState or None
        Seeds every stochastic step; the same seed gives the same model.
    n_jobs : int, default 1
        Parallel jobs: processes for the correspondence of the training shapes; threads for
        the forests (training, and scoring: :meth:`segment` gives it to the detector and
        the regional stage) and for the regional stage's validation cuts. Neither the model
        nor a segmentation depends on it, to the bit. On the hippocampus (2 cores) a case
        takes about 0.9 times as long on 2 threads as on one.
    memory_limit_gb : float or None, default None
        Memory (GiB) one image may take in :meth:`fit` and :meth:`segment`; the estimate is
        checked before the work starts and a larger one is refused with
        :class:`~medseg.errors.ResourceLimitError`, which says what to lower. None: the
        environment variable ``MEDSEG_MEMORY_LIMIT_GB`` if set, else half the machine's
        memory. A setting of this machine, not saved with the model.

    Attributes
    ----------
    landmarks_ : (S, N, 3) float array, mm
        Training landmarks in correspondence.
    cases_ : list of str
        Training cases used; ``rejected_`` maps the others to the reason.
    detector_ : LandmarkDetector
    prior_ : TripletPrior
    orientation_ : OrientationPrior or None
        None for a model saved before the handedness term existed (format version 1).
    boundary_ : BoundaryStage or None
        The regional stage; None when trained with ``boundary=False`` or saved before it
        existed (format versions 1-4).
    frame_ : ShapeFrame or None
        The shape's frame, fitted on ``landmarks_`` and the training images; None for a
        model saved before it existed (format versions 1-3), which then runs one pass.
    appearance_ : FrameAppearance or None
        The training images' mean in the frame and their held-out correlations with it
        (``appearance_check``); None for a model saved before it existed (versions 1-6).
    shape_model_ : ActiveShapeModel or None
        The refining active shape model, fitted on ``landmarks_``; None for a model saved
        before it existed (format versions 1 and 2).
    template_mask_ : SimpleITK image
        Label map of the template (reference) case: the values of ``labels`` when there
        are several (the output's sub-labels), else 1 inside.
    template_landmarks_ : (N, 3) float array, mm
    template_surface_ : tuple of ((V, 3) float array, (F, 3) int array)
    """

    def __init__(
        self,
        n_landmarks: int | None = None,
        *,
        labels: tuple[int, ...] = (1,),
        n_candidates: int = 15,
        cliques: str = "knn",
        density: str = "gmm",
        invariant: str = "distance_size",
        alpha: float = 1.0,
        orientation_weight: float = 1.0,
        orientation_sigma_mm: float = 1.0,
        refine_levels: int = 2,
        n_hypotheses: int = 4,
        hypothesis_quantile: float | None = 0.9,
        frame_passes: int = 0,
        appearance_check: bool = True,
        boundary: bool = True,
        landmark_noise_mm: float = 1.5,
        n_noise_copies: int = 10,
        n_estimators: int = 20,
        augment_poses: int = 2,
        smoothing: float = 0.0,
        max_iter: int = 100,
        mrf_method: str = "mplp",
        random_state=None,
        n_jobs: int = 1,
        memory_limit_gb: float | None = None,
    ):
        self.n_landmarks = n_landmarks
        self.labels = labels
        self.n_candidates = n_candidates
        self.cliques = cliques
        self.density = density
        self.invariant = invariant
        self.alpha = alpha
        self.orientation_weight = orientation_weight
        self.orientation_sigma_mm = orientation_sigma_mm
        self.refine_levels = refine_levels
        self.n_hypotheses = n_hypotheses
        self.hypothesis_quantile = hypothesis_quantile
        self.frame_passes = frame_passes
        self.appearance_check = appearance_check
        self.boundary = boundary
        self.landmark_noise_mm = landmark_noise_mm
        self.n_noise_copies = n_noise_copies
        self.n_estimators = n_estimators
        self.augment_poses = augment_poses
        self.smoothing = smoothing
        self.max_iter = max_iter
        self.mrf_method = mrf_method
        self.random_state = random_state
        self.n_jobs = n_jobs
        self.memory_limit_gb = memory_limit_gb

    # -- training ---------------------------------------------------------------------------

    def fit(
        self, cohort: Cohort, *, landmark_source: str = "auto", progress: bool = False
    ) -> ShapePriorSegmenter:
        """Learn landmarks, detectors, prior, template and refining shape model from a cohort.

        Parameters
        ----------
        cohort : Cohort
            Images with label maps (and optionally landmarks) of one structure.
        landmark_source : {"auto", "cohort", "labels"}, default "auto"
            "cohort" uses the landmarks each case carries (user files, the phantom's ground
            truth); "labels" computes landmarks in correspondence from the label maps (cases
            whose correspondence fails are rejected, see ``rejected_``); "auto" takes the
            cohort's landmarks when every case has them, else the label maps.
        progress : bool, default False
            Show progress bars.
        """
        if landmark_source not in ("auto", "cohort", "labels"):
            raise ParameterError("`landmark_source` must be 'auto', 'cohort' or 'labels'.")
        weight, sigma = float(self.orientation_weight), float(self.orientation_sigma_mm)
        if not (np.isfinite(weight) and weight >= 0):
            raise ParameterError(f"`orientation_weight` must be finite and >= 0; got {weight}")
        if not (np.isfinite(sigma) and sigma > 0):
            raise ParameterError(f"`orientation_sigma_mm` must be finite and > 0; got {sigma}")
        self._check_refinement()
        if len(cohort) < MIN_TRAINING_CASES:
            raise CohortError(
                f"cohort {cohort.name!r} has {len(cohort)} cases; training needs at least "
                f"{MIN_TRAINING_CASES}"
            )
        rng = check_random_state(self.random_state)
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        images, masks, label_maps = [], [], []
        for case in tqdm(cohort, desc="reading cases", disable=not progress):
            image = case.load_image()
            images.append(image)
            label_map = case.load_label()
            masks.append(select_labels(label_map, self.labels, name=str(case.label)))
            label_maps.append(label_values(label_map, self.labels))
        timings["read"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        given = [case.load_landmarks() for case in cohort]
        use_given = landmark_source == "cohort" or (
            landmark_source == "auto" and all(lm is not None for lm in given)
        )
        if use_given:
            landmarks = cohort_landmarks(cohort)
            keep = np.ones(len(landmarks), dtype=bool)
            ref = _procrustes_medoid(landmarks)
            self.rejected_ = {}
        else:
            corr = landmarks_from_labels(
                masks,
                n_landmarks=self.n_landmarks,
                labels=(1,),
                random_state=rng,
                n_jobs=self.n_jobs,
            )
            keep = ~np.asarray(corr.failed)
            landmarks = np.asarray(corr.landmarks)
            ref = int(corr.reference_index)
            self.rejected_ = {
                cohort[i].case_id: f"correspondence residual {corr.residuals_mm[i]:.2f} mm"
                for i in np.flatnonzero(~keep)
            }
        if keep.sum() < MIN_TRAINING_CASES:
            raise CohortError(
                f"only {int(keep.sum())} cases of {cohort.name!r} have landmarks in "
                f"correspondence; training needs at least {MIN_TRAINING_CASES}"
            )
        self.cases_ = [cohort[i].case_id for i in np.flatnonzero(keep)]
        self.landmarks_ = landmarks[keep]
        self.template_mask_ = label_maps[ref]
        self.template_landmarks_ = landmarks[ref]
        self.template_surface_ = label_surface(masks[ref])
        timings["landmarks"] = time.perf_counter() - t0

        kept_images = [images[i] for i in np.flatnonzero(keep)]
        _memory.check_fit_memory(
            kept_images,
            self.landmarks_,
            cliques=self.cliques,
            n_candidates=self.n_candidates,
            method=self.mrf_method,
            orientation=self._uses_orientation(),
            limit=_memory.configured_limit(self.memory_limit_gb),
        )

        t0 = time.perf_counter()
        self.detector_ = LandmarkDetector(
            n_estimators=self.n_estimators,
            augment_poses=self.augment_poses,
            random_state=rng,
            n_jobs=self.n_jobs,
        ).fit(kept_images, list(self.landmarks_))
        timings["detectors"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        self.prior_ = TripletPrior(
            cliques=self.cliques,
            density=self.density,
            invariant=self.invariant,
            alpha=self.alpha,
            random_state=rng,
        ).fit(_jittered(self.landmarks_, self.landmark_noise_mm, self.n_noise_copies, rng))
        directions = [
            gradient_directions(image, points, sigma_mm=self.orientation_sigma_mm)
            for image, points in zip(kept_images, self.landmarks_, strict=True)
        ]
        self.orientation_ = OrientationPrior().fit(
            self.landmarks_, np.stack(directions), cliques=self.prior_.cliques_
        )
        timings["prior"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        self.shape_model_ = ActiveShapeModel(n_levels=_SHAPE_MODEL_LEVELS).fit(
            self.landmarks_, kept_images
        )
        timings["shape_model"] = time.perf_counter() - t0
        self.frame_ = ShapeFrame.fit(self.landmarks_, kept_images)
        self.appearance_ = FrameAppearance().fit(self.frame_, kept_images, self.landmarks_)
        self.boundary_ = None
        if self.boundary:
            t0 = time.perf_counter()
            self.boundary_ = BoundaryStage(
                n_estimators=max(1, round(_BOUNDARY_TREES * self.n_estimators)),
                random_state=rng,
                n_jobs=self.n_jobs,
            ).fit(
                self.frame_,
                self.template_mask_,
                self.template_landmarks_,
                kept_images,
                [label_maps[i] for i in np.flatnonzero(keep)],
                self.landmarks_,
                groups=[str(cohort[i].subject) for i in np.flatnonzero(keep)],
            )
            timings["boundary"] = time.perf_counter() - t0
        self.fit_timings_ = timings
        return self

    # -- inference --------------------------------------------------------------------------

    def segment(
        self, image, *, use_prior: bool = True, candidates: CandidateSet | None = None
    ) -> Segmentation:
        """Segment one image, with no pose initialisation.

        Parameters
        ----------
        image : path, SimpleITK image or nibabel image
        use_prior : bool, default True
            False places each landmark at its best candidate (the detection-only
            baseline); True minimises the higher-order MRF.
        candidates : CandidateSet, optional
            Candidates already detected in this image (``Segmentation.candidates`` of an
            earlier call, or of the first pass with ``frame_passes``), so that variants of
            the inference do not detect twice.
        """
        self._check_is_fitted()
        self._check_refinement()
        source = image
        image = read_image(image)
        self._share_threads()
        found = self._locate(image, use_prior=use_prior, candidates=candidates)
        if use_prior and self._uses_frame():
            found = in_frame_passes(
                self, image, found, n_passes=int(self.frame_passes), locate=self._locate
            )
        appearance = None
        if use_prior and self._uses_appearance():
            found, appearance = self._check_appearance(image, found)
        t0 = time.perf_counter()
        shape_label = warp_labels(
            self.template_mask_,
            self.template_landmarks_,
            found.landmarks,
            image,
            smoothing=self.smoothing,
        )
        vertices, faces = self.template_surface_
        surface = warp_surface(
            vertices, faces, self.template_landmarks_, found.landmarks, smoothing=self.smoothing
        )
        found.timings["reconstruction"] = time.perf_counter() - t0
        label, quality = shape_label, None
        if use_prior and self._uses_boundary():
            t0 = time.perf_counter()
            refined = self.boundary_.refine(
                self.frame_, self.template_mask_, self.template_landmarks_, image, found.landmarks
            )
            label, quality = refined.label, _quality(found, refined)
            found.timings["boundary"] = time.perf_counter() - t0
        return Segmentation(
            label=as_input_type(label, like=source),
            shape_label=as_input_type(shape_label, like=source),
            landmarks=found.landmarks,
            surface=surface,
            candidates=found.candidates,
            mrf=found.mrf,
            confidence=found.confidence,
            timings=found.timings,
            chosen=found.chosen,
            hypotheses=found.hypotheses,
            image=image,
            frame_pose=found.frame_pose,
            quality=quality,
            appearance=appearance,
        )

    def _share_threads(self) -> None:
        """The forests' threads at prediction: ``n_jobs``, for the detector and the stage."""
        self.detector_.n_jobs = self.n_jobs
        if getattr(self, "boundary_", None) is not None:
            self.boundary_.n_jobs = self.n_jobs

    def _locate(
        self, image, *, use_prior: bool = True, candidates: CandidateSet | None = None
    ) -> Located:
        """The landmarks in ``image`` (a SimpleITK image): detection, MRF, refinement."""
        limit = _memory.configured_limit(self.memory_limit_gb)
        if candidates is None:
            _memory.check_detection_memory(image, self.detector_, limit)
        timings: dict[str, float] = {}

        t0 = time.perf_counter()
        cands = candidates
        if cands is None:
            cands = self.detector_.candidates(image, n_candidates=self.n_candidates)
        timings["detection"] = time.perf_counter() - t0

        n = cands.positions.shape[0]
        unaries = cands.unaries()
        result = None
        if use_prior:
            t0 = time.perf_counter()
            _memory.check_mrf_memory(
                n,
                len(self.prior_.cliques_),
                cands.positions.shape[1],
                method=self.mrf_method,
                orientation=self._uses_orientation(),
                limit=limit,
            )
            tables = self.prior_.potential_tables(cands.positions, max_table_bytes=limit)
            if self._uses_orientation():
                directions = gradient_directions(
                    image, cands.positions.reshape(-1, 3), sigma_mm=self.orientation_sigma_mm
                ).reshape(cands.positions.shape)
                handedness = self.orientation_.tables(cands.positions, directions)
                handedness *= float(self.orientation_weight)  # in place: no third table
                tables += handedness
                del handedness
            timings["potentials"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            problem = MRF.from_triplets(unaries, self.prior_.cliques_, tables)
            # the MRF's memory was checked above against the limit; solve's own budget
            # (a fixed 64 MiB of kernel blocks in its estimate) only needs raising with it
            budget = max(DEFAULT_MAX_BYTES, memory_limit_bytes() if limit is None else limit)
            result = solve(
                problem, method=self.mrf_method, max_iter=self.max_iter, max_bytes=budget
            )
            timings["mrf"] = time.perf_counter() - t0
            choice = np.asarray(result.x)
            confidence = margin(result.min_marginals)
        else:
            choice = np.argmin(unaries, axis=1)
            confidence = margin(unaries)
        landmarks = cands.positions[np.arange(n), choice]
        chosen = landmarks
        hypotheses: list[Hypothesis] = []
        if use_prior and self.refine_levels and self.shape_model_ is not None:
            check_not_collapsed(chosen)
            t0 = time.perf_counter()
            hypotheses = refined_hypotheses(
                self.shape_model_,
                image,
                cands.positions,
                unaries,
                self.prior_.cliques_,
                tables,
                result,
                n_hypotheses=self.n_hypotheses,
                refine_levels=self.refine_levels,
                solve_options={
                    "method": self.mrf_method,
                    "max_iter": self.max_iter,
                    "max_bytes": budget,
                },
                accept_cost=self._accept_cost(),
            )
            best = min(hypotheses, key=lambda h: h.profile_cost)
            chosen, landmarks = best.chosen, best.landmarks
            timings["refinement"] = time.perf_counter() - t0
        return Located(
            candidates=cands,
            mrf=result,
            confidence=confidence,
            chosen=chosen,
            landmarks=landmarks,
            hypotheses=hypotheses,
            timings=timings,
        )

    # -- persistence ------------------------------------------------------------------------

    def save(self, path: str | Path) -> Path:
        """Write the model to a folder (JSON + NPZ + skops, checksummed, no pickle)."""
        self._check_is_fitted()
        return _persistence.save_model(self, Path(path))

    @classmethod
    def load(cls, path: str | Path) -> ShapePriorSegmenter:
        """Read a model written by :meth:`save`; checksums and format version are verified."""
        return _persistence.load_model(cls, Path(path))

    def _uses_orientation(self) -> bool:
        """Whether segment adds the handedness tables (fit always learns them)."""
        fitted_without = hasattr(self, "orientation_") and self.orientation_ is None
        return bool(self.orientation_weight) and not fitted_without

    def _check_refinement(self) -> None:
        levels = self.refine_levels
        if (
            isinstance(levels, bool)
            or not isinstance(levels, (int, np.integer))
            or not (0 <= levels <= _SHAPE_MODEL_LEVELS)
        ):
            raise ParameterError(
                f"`refine_levels` must be an integer from 0 to {_SHAPE_MODEL_LEVELS}; "
                f"got {levels!r}"
            )
        n = self.n_hypotheses
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ParameterError(f"`n_hypotheses` must be an integer >= 1; got {n!r}")
        p = self.frame_passes
        if isinstance(p, bool) or not isinstance(p, (int, np.integer)) or p < 0:
            raise ParameterError(f"`frame_passes` must be an integer >= 0; got {p!r}")
        q = self.hypothesis_quantile
        if q is not None and (
            isinstance(q, bool)
            or not isinstance(q, (int, float, np.integer, np.floating))
            or not 0.0 <= q <= 1.0
        ):
            raise ParameterError(
                f"`hypothesis_quantile` must be None or a number from 0 to 1; got {q!r}"
            )

    def _accept_cost(self) -> float | None:
        """The profile cost at or below which the refined optimum is kept alone (None: the
        further hypotheses are always solved)."""
        costs = getattr(self.shape_model_, "training_costs_", None)
        if self.hypothesis_quantile is None or costs is None or not len(costs):
            return None
        return float(np.quantile(costs, float(self.hypothesis_quantile)))

    def _uses_boundary(self) -> bool:
        """Whether segment runs the regional stage (a model without one cannot)."""
        return bool(self.boundary) and getattr(self, "boundary_", None) is not None

    def _uses_appearance(self) -> bool:
        """Whether segment checks the found shape's appearance (a model without the check,
        saved before format version 7, cannot)."""
        return bool(self.appearance_check) and getattr(self, "appearance_", None) is not None

    def _check_appearance(self, image, found: Located) -> tuple[Located, dict]:
        """``found``, or the shape the active shape search finds from one of the
        registrations onto the training mean: the one that correlates best near the
        structure, when it correlates better than ``found`` and is ``found`` turned about
        itself (:meth:`FrameAppearance.prefers`); and what the check saw of it.

        The best is judged, not the best of those preferred: when it is ``found`` moved a
        little (phantom: two of the six, 0.91-0.92 near the structure, turned by 24-26
        degrees from a found shape at 0.82), ``found`` is in the right frame, and a turned
        copy that beats it by a hair (0.818 against 0.817) is not what the check is for."""
        t0 = time.perf_counter()
        check = self.appearance_
        score, before = check.scores(self.frame_, image, found.landmarks)
        seen = {"score": score, "threshold": check.threshold_, "searched": False, "replaced": False}
        if score < check.threshold_:
            levels = int(self.refine_levels) or None  # 0: the search's every level
            shapes = [
                self.shape_model_.search(image, start=start, levels=levels).landmarks
                for start in check.search(self.frame_, image, found.landmarks, n_jobs=self.n_jobs)
            ]
            near = [check.score(self.frame_, image, shape) for shape in shapes]
            moved = shapes[int(np.argmax(near))]  # the first of equals: the search's order
            better, judged = check.prefers(
                self.frame_, image, found.landmarks, moved, found_scores=(score, before)
            )
            replaced = better and not collapsed(moved)
            seen |= {"searched": True, "box_score": before, **judged, "replaced": replaced}
            if replaced:
                found = replace(found, landmarks=moved)
        found.timings["appearance"] = time.perf_counter() - t0
        return found, seen

    def _uses_frame(self) -> bool:
        """Whether segment runs passes in the shape's frame (a model without one cannot)."""
        return bool(self.frame_passes) and getattr(self, "frame_", None) is not None

    def _check_is_fitted(self) -> None:
        if not hasattr(self, "detector_"):
            raise NotFittedError(
                "this ShapePriorSegmenter is not fitted yet: call fit(cohort) or load a model"
            )


def load_model(path: str | Path) -> ShapePriorSegmenter:
    """Load a segmentation model saved with :meth:`ShapePriorSegmenter.save`."""
    return ShapePriorSegmenter.load(path)


def _quality(found: Located, refined) -> dict:
    """``Segmentation.quality``: the regional stage's score and the evidence beside it."""
    best = min(found.hypotheses, key=lambda h: h.profile_cost) if found.hypotheses else None
    score = refined.score if np.isfinite(refined.score) else None  # JSON has no NaN
    return {
        "score": score,
        "flagged": score is not None and score > QUALITY_THRESHOLD,
        "disagreement": refined.disagreement,
        "change": refined.change,
        "profile_cost": None if best is None else float(best.profile_cost),
        "mrf_energy": float(found.mrf.energy),
        "mrf_gap": float(found.mrf.gap),
    }


def _procrustes_medoid(shapes: np.ndarray) -> int:
    """Index of the shape with the smallest summed Procrustes disparity to the others."""
    n = len(shapes)
    disparity = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1, n):
            disparity[i, j] = disparity[j, i] = procrustes_disparity(shapes[i], shapes[j])
    return int(np.argmin(disparity.sum(axis=1)))


def _jittered(shapes: np.ndarray, sigma: float, copies: int, rng) -> np.ndarray:
    """``copies`` noisy versions of every shape (isotropic Gaussian, ``sigma`` mm)."""
    if sigma <= 0 or copies < 1:
        return shapes
    noise = rng.normal(scale=sigma, size=(copies,) + shapes.shape)
    return (shapes[None] + noise).reshape((-1,) + shapes.shape[1:])
