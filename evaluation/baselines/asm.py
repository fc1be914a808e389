"""The standard active shape model baseline (Cootes et al. 1995), as a user of ASM runs it.

The model itself (point distribution model, profile models, multi-resolution search) is
:class:`medseg.shape.ActiveShapeModel`, which the segmenter also uses to refine its
landmarks. The baseline starts the search where a user would, with no knowledge of the
pose: the mean shape at the physical centre of the image, in the mean training orientation
and size. The label map comes from the same thin-plate-spline reconstruction as the
segmenter (:func:`medseg.reconstruction.warp_labels`), with the training case closest to
the mean shape as template; with ``boundary=True`` the segmenter's regional stage
(:class:`medseg.segmenter.BoundaryStage`, in the frame of the ASM's landmarks) refines it,
so that the two methods can be compared with the same last stage.
"""

from __future__ import annotations

import inspect
import time
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk
from tqdm.auto import tqdm

from medseg.errors import CohortError, NotFittedError
from medseg.frame import ShapeFrame
from medseg.io import label_values, read_image
from medseg.reconstruction import warp_labels
from medseg.segmenter import BoundaryStage
from medseg.shape import ActiveShapeModel

__all__ = ["ASMBaseline", "ASMResult"]

# The baseline's parameters of the same names configure the model.
_ASM_PARAMETERS = tuple(inspect.signature(ActiveShapeModel).parameters)


@dataclass
class ASMResult:
    """The result of :meth:`ASMBaseline.segment`.

    Attributes
    ----------
    label : SimpleITK image, uint8
        The template carried onto ``landmarks`` (TPS), on the input's grid, refined by the
        regional stage with ``boundary=True``.
    shape_label : SimpleITK image, uint8
        The template carried onto ``landmarks``, before the regional stage.
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
    shape_label: sitk.Image | None = None


class ASMBaseline:
    """Active shape model search from the image centre, then the segmenter's TPS.

    Parameters
    ----------
    labels : tuple of int, default (1,)
        Labels of the training label maps forming the structure.
    variance, limit, profile_half, search_half, step_mm, n_levels, max_iter
        Those of :class:`medseg.shape.ActiveShapeModel`.
    smoothing : float, default 0.0
        Thin-plate spline smoothing of the reconstruction.
    boundary : bool, default False
        Refine the label map with the segmenter's regional stage, trained on the same
        cases (in the frame of the ASM's landmarks).
    random_state : int, RandomState or None
        Seeds the regional stage; nothing in the ASM itself is random.

    Attributes
    ----------
    model_ : medseg.shape.ActiveShapeModel
    template_mask_ : SimpleITK image
    template_landmarks_ : (N, 3) float array, mm
    frame_ : ShapeFrame or None
    boundary_ : BoundaryStage or None
        With ``boundary=True``.
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
        boundary: bool = False,
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
        self.boundary = boundary
        self.random_state = random_state

    def fit(self, cohort, *, progress: bool = False) -> ASMBaseline:
        """Learn the model from a cohort whose cases carry landmarks in correspondence.

        Parameters
        ----------
        cohort : Cohort
            Cases with images, label maps and landmarks ``(N, 3)`` mm
            (``case.load_landmarks()``).
        progress : bool, default False
        """
        shapes, images = [], []
        for case in tqdm(cohort, desc="reading cases", disable=not progress):
            lm = case.load_landmarks()
            if lm is None:
                raise CohortError(
                    f"case {case.case_id!r} has no landmarks: the ASM trains on landmarks in "
                    "correspondence (give landmark files, or run it through medseg-evaluate, "
                    "which computes them from the label maps)"
                )
            shapes.append(np.asarray(lm, dtype=float))
            images.append(read_image(case.load_image()))
        if len({s.shape for s in shapes}) > 1:
            raise CohortError("training cases carry different numbers of landmarks")
        self.model_ = ActiveShapeModel(
            **{name: getattr(self, name) for name in _ASM_PARAMETERS}
        ).fit(np.asarray(shapes) if shapes else np.empty((0, 0, 3)), images, progress=progress)
        ref = self.model_.closest_to_mean_
        self.template_mask_ = label_values(cohort[ref].load_label(), self.labels)
        self.template_landmarks_ = shapes[ref].copy()
        self.frame_ = self.boundary_ = None
        if self.boundary:
            self.frame_ = ShapeFrame.fit(np.asarray(shapes), images)
            self.boundary_ = BoundaryStage(random_state=self.random_state).fit(
                self.frame_,
                self.template_mask_,
                self.template_landmarks_,
                images,
                [label_values(case.load_label(), self.labels) for case in cohort],
                np.asarray(shapes),
                groups=[str(case.subject) for case in cohort],
            )
        return self

    def segment(self, image, **_ignored) -> ASMResult:
        """Search the image from the mean shape at its centre, with unit pose."""
        if not hasattr(self, "model_"):
            raise NotFittedError("this ASMBaseline is not fitted yet: call fit(cohort)")
        t_start = time.perf_counter()
        image = read_image(image)
        found = self.model_.search(image)
        timings = {"search": time.perf_counter() - t_start}
        t0 = time.perf_counter()
        shape_label = warp_labels(
            self.template_mask_,
            self.template_landmarks_,
            found.landmarks,
            image,
            smoothing=self.smoothing,
        )
        timings["reconstruction"] = time.perf_counter() - t0
        label = shape_label
        if self.boundary_ is not None:
            t0 = time.perf_counter()
            label = self.boundary_.refine(
                self.frame_, self.template_mask_, self.template_landmarks_, image, found.landmarks
            ).label
            timings["boundary"] = time.perf_counter() - t0
        return ASMResult(
            label=label,
            shape_label=shape_label,
            landmarks=found.landmarks,
            shape_parameters=found.shape_parameters,
            pose=found.pose,
            n_iter=found.n_iter,
            timings=timings,
        )
