"""What a segmentation returns: the label map, the landmarks, and the evidence behind them."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import SimpleITK as sitk

from medseg.detection import CandidateSet
from medseg.geometry import Similarity
from medseg.mrf import SolveResult

__all__ = ["Hypothesis", "Segmentation", "Located"]


@dataclass(frozen=True)
class Hypothesis:
    """One MRF solution and its active-shape refinement.

    Attributes
    ----------
    labels : (N,) int array
        The candidate chosen for each landmark.
    chosen : (N, 3) float array, mm
        Those candidates' positions.
    landmarks : (N, 3) float array, mm
        The refined landmarks.
    profile_cost : float
        How well the refined instance fits the image's boundary profiles (lower is better,
        :meth:`medseg.shape.ActiveShapeModel.profile_cost`).
    """

    labels: np.ndarray
    chosen: np.ndarray
    landmarks: np.ndarray
    profile_cost: float


@dataclass
class Segmentation:
    """The result of :meth:`ShapePriorSegmenter.segment`.

    Attributes
    ----------
    label : image
        Label map (uint8) in the input image's geometry, of the input's type (SimpleITK
        image, or nibabel image when a nibabel image was given): the training labels' own
        values for a model of several labels (hippocampus: 1 anterior, 2 posterior), else
        1 = structure. Refined by the regional stage when the model has one.
    shape_label : image
        The shape-only label map (the template warped onto ``landmarks``), before the
        regional stage; the same as ``label`` without it.
    landmarks : (N, 3) float array, mm, (x, y, z)
        The landmarks found (the MRF's choice refined by the active shape model, see
        ``refine_levels``), in the input's physical space.
    surface : pyvista.PolyData
        The template surface warped onto ``landmarks`` (mm).
    candidates : CandidateSet
        The candidate positions ``(N, L, 3)`` and probabilities ``(N, L)`` per landmark.
    mrf : SolveResult or None
        Energy, lower bound, relative gap, iterations of the MRF solve (None without prior).
    confidence : (N,) float array
        Per landmark: the margin between its two best min-marginal energies (with the
        prior) or unary costs (without), i.e. what moving it to its second-best candidate
        costs at least; small values mark uncertain landmarks.
    timings : dict
        Seconds spent in each stage.
    chosen : (N, 3) float array, mm
        The candidates the MRF (or, without prior, the detectors) chose, before the
        active-shape refinement that gives ``landmarks`` (equal to them without it).
    hypotheses : list of Hypothesis
        With refinement: the MRF solutions that were refined, the first being the MRF's
        optimum (``mrf``; alone when it fit well enough, see ``hypothesis_quantile``), each
        labelling once; ``landmarks`` come from the one with the lowest profile cost. Empty
        without refinement.
    quality : dict or None
        With the regional stage: ``score`` (how many standard deviations beyond the
        held-out training cases this case's disagreement between image and shape lies,
        :class:`~medseg.segmenter.BoundaryStage`), ``flagged`` (``score`` above
        :data:`~medseg.segmenter.QUALITY_THRESHOLD`: likely wrong), the two signals behind
        it (``disagreement``, ``change``) and, for the record, ``profile_cost``,
        ``mrf_energy`` and ``mrf_gap``. None without the stage; ``score`` None for a model
        of too few training cases to compare with.
    frame_pose : Similarity or None
        With ``frame_passes``: the similarity from the input's physical space (mm) into the
        shape's frame in which the last pass ran (the result's landmarks, candidates and
        hypotheses are mapped back into the input's space). None when no pass ran in the
        frame.
    appearance : dict or None
        With the appearance check (``appearance_check``): ``score``, the correlation of the
        image near the found landmarks, in the shape's frame, with the training images'
        mean; ``threshold``, below which a better placement was searched (``searched``);
        then ``search_score``, the searched landmarks' correlation near the shape,
        ``box_score`` and ``search_box_score``, the found and the searched landmarks'
        correlations over the frame's box, ``turn_deg``, the rotation between the found and
        the searched shape, and ``replaced``, whether the searched landmarks (better on
        both, and turned by at least ``MIN_TURN_DEG``) replaced the found ones
        (``landmarks`` then no longer come from ``chosen``). None without the check.
    """

    label: Any
    landmarks: np.ndarray
    surface: Any
    candidates: CandidateSet
    mrf: SolveResult | None
    confidence: np.ndarray
    timings: dict = field(default_factory=dict)
    chosen: np.ndarray | None = None
    hypotheses: list = field(default_factory=list)
    image: sitk.Image | None = field(default=None, repr=False)
    frame_pose: Similarity | None = None
    shape_label: Any = None
    quality: dict | None = None
    appearance: dict | None = None

    def plot(self, *, axis: int = 0, index: int | None = None):
        """Image, label and overlay of one slice with the nearby landmarks (a matplotlib
        Figure; by default the slice with the largest labelled area)."""
        from medseg.viz import plot_slice

        return plot_slice(self.image, self.label, axis=axis, index=index, landmarks=self.landmarks)

    def show(self, **kwargs):
        """Interactive 3D view of the surface and landmarks (pyvista)."""
        import pyvista as pv

        plotter = pv.Plotter(**kwargs)
        plotter.add_mesh(self.surface, color="tan", opacity=0.8)
        plotter.add_points(
            self.landmarks, color="red", point_size=10, render_points_as_spheres=True
        )
        return plotter.show()


@dataclass
class Located:
    """What one pass of detection, MRF and refinement found in one image (internal).

    The fields of :class:`Segmentation` before the reconstruction, in the physical space
    of the image the pass ran on.
    """

    candidates: CandidateSet
    mrf: SolveResult | None
    confidence: np.ndarray
    chosen: np.ndarray
    landmarks: np.ndarray
    hypotheses: list
    timings: dict
    frame_pose: Similarity | None = None
