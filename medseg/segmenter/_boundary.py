"""The regional stage: from the landmarks to the boundary, in the shape's own frame.

The thin-plate spline carries the template onto the landmarks, and between them no image
evidence shapes the result: perfect landmarks stop at about 0.90 Dice on the hippocampus.
This stage adds the evidence (Xiang, Wang et al., ISBI 2012, regional terms factorised
into the model):

1. the image is resampled into the frame of the landmarks found (:class:`ShapeFrame`):
   upright, at the mean size, whatever the input's pose;
2. training label maps kept in the frame (:class:`FrameAtlases`) are carried there by
   their thin-plate splines and vote (the template alone when there are none); the vote's
   signed distances give a narrow band around it and the shape's opinion of every voxel,
   and its shares are features;
3. a voxel classifier (:class:`medseg.detection.VoxelClassifier`) gives each voxel of the
   band its label probabilities, and a second one, which also sees the first one's answer
   around each voxel (auto-context, Tu & Bai 2010), gives them again;
4. a multi-label graph cut (alpha-expansion, :func:`medseg.mrf.potts_expansion`; exact
   s-t min cut for one label) minimises ``-log p + shape term`` with contrast-sensitive
   Potts terms between neighbours;
5. the landmarks follow the boundary from the warped template to the cut (coherent point
   drift between the two surfaces) and steps 1-4 run once more from them (``rounds``), so
   that the template and its band sit where the image, not the detectors, put the boundary;
6. the labels go back to the input's exact grid through their signed distances
   (linearly interpolated), not by nearest neighbour.

The classifier learns from training images seen through landmarks jittered by about the
error of found landmarks, so it meets at training the misplaced templates it meets at test
time (cross-fitted segmenter outputs would be truer, at the cost of training the whole
segmenter once per fold), and from copies of them in a random pose, size and field of view
(``pose_copies``), so that an image resampled before it reaches the stage is no stranger
to it. The cut's two weights and its background cost (which undoes the
shrinking of a classifier and a boundary term that side with background where in doubt) are
chosen on training cases the classifier did not see, by the Dice they give.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from itertools import product
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy import ndimage
from sklearn.utils import check_random_state

from medseg.correspondence import follow_boundary, label_surface
from medseg.detection import (
    CONTRAST_RING_MM,
    VoxelClassifier,
    context_features,
    voxel_features,
)
from medseg.errors import ImageGeometryError, LabelError, ModelFileError, ParameterError
from medseg.frame import ShapeFrame
from medseg.geometry import Similarity
from medseg.io import check_format, load_arrays, random_pose, save_arrays
from medseg.mrf import grid_edges, potts_expansion
from medseg.segmenter._atlases import FrameAtlases
from medseg.segmenter._frame_view import FrameView, frame_view, template_values, to_input
from medseg.threads import thread_map

__all__ = ["BoundaryStage", "Refined"]

_MIN_PROBABILITY = 1e-3  # floor of the classifier's probabilities in -log p
#: validation cases the quality score needs (a model of fewer training cases has none)
MIN_REFERENCE_CASES = 5
_MIN_SPREAD = 0.02  # floor of the signals' spread: cases that happen to agree closely
# the posed training copies (``pose_copies``): any rotation, the evaluation's scales and padding
_POSE_ANGLE_DEG = 180.0
_POSE_SCALES = (0.8, 1.25)
_POSE_PAD_MM = 15.0


def _wrong_side(distances: np.ndarray) -> np.ndarray:
    """(1 + K, n) mm by which each voxel lies outside what the template gives each label:
    background inside the union, label k outside its own region."""
    union, own = distances[0], distances[1:]
    return np.vstack([np.maximum(-union, 0.0)[None], np.maximum(own, 0.0)])


def _contrast_weights(values: np.ndarray, edges: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Potts weights ``exp(-beta (I_u - I_v)^2) / length`` (Boykov & Jolly 2001), with
    ``beta`` the inverse of twice the mean squared difference along the edges."""
    diff2 = (values[edges[:, 0]] - values[edges[:, 1]]) ** 2
    mean = float(diff2.mean()) if len(diff2) else 0.0
    beta = 0.5 / mean if mean > 0 else 0.0
    return np.exp(-beta * diff2) / lengths


def _cut(
    view: FrameView,
    probabilities: np.ndarray,
    nodes: np.ndarray,
    *,
    band_mm: float,
    smoothness: float,
    shape_weight: float,
    foreground_bias: float = 0.0,
) -> np.ndarray:
    """The labels (values, on the frame grid) minimising the stage's energy.

    ``probabilities`` are the classifier's (n, 1 + K) over the voxels ``nodes`` (a
    (Z, Y, X) bool array: the domain and its outer layer, which is held to background);
    ``foreground_bias`` is added to every voxel's cost of background.
    """
    distances = view.distances[:, nodes]
    unary = -np.log(np.clip(probabilities, _MIN_PROBABILITY, None)).T
    unary = unary + shape_weight * _wrong_side(distances)
    unary[0] += foreground_bias
    unary[1:, distances[0] > band_mm] = np.inf  # the outer layer: background
    unary[0, distances[0] < -band_mm] = np.inf  # deep inside: never background
    spacing = np.asarray(view.upright.GetSpacing(), dtype=float)[::-1]
    edges, lengths = grid_edges(nodes, spacing)
    intensities = sitk.GetArrayViewFromImage(view.upright)[nodes].astype(float)
    weights = smoothness * _contrast_weights(intensities, edges, lengths)
    choice = potts_expansion(unary.T, edges, weights)  # from each voxel's cheapest label
    out = np.zeros(view.shape.shape, dtype=np.uint8)
    out[nodes] = np.asarray((0,) + view.values, dtype=np.uint8)[choice]
    return out


def _dice_scores(predicted: np.ndarray, truth: np.ndarray, values: tuple) -> float:
    """Mean of the union's Dice and, with several labels, the labels' mean Dice."""

    def dice(a, b):
        total = int(a.sum()) + int(b.sum())
        return 1.0 if total == 0 else 2.0 * int(np.logical_and(a, b).sum()) / total

    union = dice(predicted > 0, truth > 0)
    if len(values) == 1:
        return union
    return 0.5 * (union + float(np.mean([dice(predicted == v, truth == v) for v in values])))


def _signals(view: FrameView, probabilities: np.ndarray, nodes: np.ndarray, cut: np.ndarray):
    """How far the image agrees with the shape: ``(disagreement, change)``.

    ``disagreement``: 1 minus the classifier's mean probability, over the voxels the cut
    decides, of the label the warped template gives them; ``change``: 1 minus the Dice of
    the warped template's union and the cut's. A template on the wrong anatomy meets a
    classifier that does not see the structure where the template puts it, and a cut that
    has to move far.
    """
    column = np.zeros(256, dtype=np.intp)  # label value -> column of ``probabilities``
    column[list(view.values)] = np.arange(1, len(view.values) + 1)
    said = column[view.shape[nodes]]
    if not len(said):  # the template left the frame's grid: nothing agrees
        return 1.0, 1.0
    agreement = float(probabilities[np.arange(len(said)), said].mean())
    a, b = view.shape > 0, cut > 0
    dice = 2.0 * float(np.logical_and(a, b).sum()) / max(1, int(a.sum()) + int(b.sum()))
    return 1.0 - agreement, 1.0 - dice


def _follow(view: FrameView, labels: np.ndarray, landmarks: np.ndarray) -> np.ndarray | None:
    """``landmarks`` (input mm) moved with the boundary from the view's warped template to
    the cut ``labels`` (both on the frame's grid), in input mm; None when either has no
    boundary to follow."""
    surfaces = []
    for mask in (view.shape > 0, labels > 0):
        image = sitk.GetImageFromArray(mask.astype(np.uint8))
        image.CopyInformation(view.upright)
        try:
            surfaces.append(label_surface(image, labels=1, keep_largest=True))
        except LabelError:
            return None
    return view.pose.inverse(follow_boundary(view.pose(landmarks), *surfaces))


class _Joined:
    """A training view's features and its auto-context columns, joined only for the rows
    taken: joined once for every view, they were a second copy of all the features while
    the first still existed (a fit on 30 hippocampus cases peaked at 1.15 GB of arrays,
    0.78 GB with this; the same stage to the bit)."""

    def __init__(self, features: np.ndarray, context: np.ndarray):
        self.features, self.context = features, context

    def __len__(self) -> int:
        return len(self.features)

    def __getitem__(self, rows) -> np.ndarray:
        return np.hstack([self.features[rows], self.context[rows]])

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        joined = np.hstack([self.features, self.context])
        return joined if dtype is None else joined.astype(dtype)


@dataclass
class Refined:
    """What :meth:`BoundaryStage.refine` returns.

    Attributes
    ----------
    label : SimpleITK image
        The refined label map, on the input's grid.
    disagreement, change : float
        :func:`_signals` of this case.
    score : float
        The larger of their z-scores against the training cases the classifier did not
        see (``BoundaryStage.reference_``; spreads of at least 0.02): how unusual this
        case's disagreement between image and shape is; above 3, the segmentation is
        likely wrong. NaN when fewer than :data:`MIN_REFERENCE_CASES` were held out.
    """

    label: sitk.Image
    disagreement: float
    change: float
    score: float


class BoundaryStage:
    """Voxel classifier and graph cut in the shape's frame (see the module docstring).

    Parameters
    ----------
    band_mm : float, default 4.0
        Half-width of the band around the warped template that the cut may change.
    jitter_mm : float, default 1.0
        Standard deviation of the noise added to the training landmarks (per landmark, and
        once more as a shift of the whole shape) before the template is warped onto them.
    spacing_ratio : float, default 0.7
        The stage's grid spacing as a fraction of the frame's (the training images' median
        spacing). Finer than the images, so that labels lose little on their way into the
        frame and back: the true hippocampus labels come back at 0.968 Dice through a grid
        of the images' spacing, 0.999 at 0.7 of it.
    classifier : {"forest", "boosting"}, default "forest"
        The voxel classifier's method (:class:`medseg.detection.VoxelClassifier`).
    n_estimators : int, default 15
        Trees of the voxel classifier's forest.
    n_iterations : int, default 100
        Iterations of its boosting.
    rows_per_case : int, default 4000
        Voxels of each training case the classifier learns from (drawn from the band, in
        equal parts from the case and its posed copies).
    pose_copies : int, default 1
        Copies of each training image in a random pose, size and field of view
        (:func:`medseg.io.random_pose`: any rotation, scale 0.8-1.25, 15 mm of padding)
        that the classifiers also learn from. The frame undoes the pose, but not what
        resampling does to the image: a test image that was resampled once already (a
        reformatted scan, a perturbation study) reaches the frame smoother, and its padding
        may lie where a training crop had tissue. Refitted on a 138-case model's training
        cases, 61 held-out cases of 40 subjects, landmarks held fixed (found on the acquired
        image, carried by the perturbation), paired against no copies: under the
        evaluation's random similarity +0.0013 Dice (s.e. 0.0007), the same transform
        without padding +0.0022 (0.0007), acquired +0.0008 (0.0007); 22 % more fitting
        time. The stage still loses about 0.006 more than the warped template there, as
        under a half-voxel shift alone (0.008), where the reference itself, resampled
        label-linearly, also changes: the perturbation study's references are uncertain
        at that level (label-linear and nearest-neighbour copies agree at Dice 0.965).
    rounds : int, default 2
        Passes of :meth:`refine`. After each but the last, the landmarks follow the
        boundary from the warped template to the cut (coherent point drift between the two
        surfaces, :func:`medseg.correspondence.follow_boundary`) and the stage runs again
        from them, so the template, its band and its shape term sit where the image put the
        boundary and no longer where the detectors put the landmarks. A round is kept only
        if its landmarks stay distinct, its cut leaves a structure and its signals
        (:attr:`Refined.score`) are not more unusual than the round before; the quality
        score is the first round's, the one that judges the found landmarks (and when the
        stage has too few validation cases for a score, every round is kept). Hippocampus,
        5-fold by subject, 199 cases, the fold models of a cross-validation with their
        stages run for 2 rounds instead of 1:
        Dice 0.8800 -> 0.8829 (+0.0029, s.e. 0.0007, better on 117 cases, worse on 81;
        every fold gained), per label 0.857 / 0.835 -> 0.860 / 0.840; the stage takes about
        twice as long (0.26 s of it to follow the boundary). Without the guard a case that
        had failed (Dice 0.19) came out empty; 3 rounds were no better than 2 (61 held-out
        cases). 1 is the single pass.
    smoothness : tuple of float
        Candidate weights of the contrast-sensitive Potts term.
    shape_weight : tuple of float
        Candidate weights (per mm) of the shape term.
    foreground_bias : tuple of float
        Candidate costs (nats) added to background at every voxel of the cut, chosen like
        the weights, after them (then the weights again at the chosen cost). Where the
        boundary is uncertain the classifier's probabilities lean to the band's majority,
        background, and the Potts term shortens the boundary: without it the hippocampus
        came out about 6 % smaller than the reference (median of 61 held-out cases), with
        the chosen cost 2 % larger (mean) and 0.004 higher in Dice.
    validation_fraction : float, default 0.25
        Training cases held out from the classifier to choose the weights and the cost.
    auto_context : bool, default True
        A second classifier on the first one's probabilities around each voxel (its
        training cases see the first classifier's answers cross-fitted on two halves).
    n_atlases : int, default 0
        Training label maps kept in the frame (:class:`FrameAtlases`) whose thin-plate
        spline vote replaces the one template's warp (band, shape term, distances) and
        whose shares are features; 0 uses the template alone. A training case never sees
        atlases of its own subject (``groups`` of :meth:`fit`). Off by default: on 30
        held-out hippocampus subjects 15 atlases took the vote before the stage from 0.816
        to 0.830 Dice, but the stage's result not past the template's (0.8695 vs 0.8693).
    atlas_patches : bool, default False
        Weight each atlas' vote at a voxel by the similarity of the two images' patches
        there (the atlases then keep their images in the frame).
    random_state : int, RandomState or None
    n_jobs : int, default 1
        Threads of the classifiers (fit and scoring) and of the validation cuts of
        :meth:`fit`; the stage and its labels do not depend on it.

    Attributes
    ----------
    classifier_ : VoxelClassifier
        The classifier whose probabilities the cut uses (the second with auto-context).
    context_ : VoxelClassifier or None
        With auto-context, the first classifier.
    atlases_ : FrameAtlases or None
        With ``n_atlases > 0``.
    values_ : tuple of int
        The label values it returns.
    smoothness_, shape_weight_, foreground_bias_ : float
        The chosen weights and background cost.
    selection_ : list of (smoothness, shape_weight, foreground_bias, score)
        The validation score of every candidate tried.
    reference_ : (V, 2) float array
        :func:`_signals` (disagreement, change) of the validation cases with the chosen
        weights: what :attr:`Refined.score` compares a case with.
    """

    def __init__(
        self,
        *,
        band_mm: float = 4.0,
        jitter_mm: float = 1.0,
        spacing_ratio: float = 0.7,
        classifier: str = "forest",
        n_estimators: int = 15,
        n_iterations: int = 100,
        rows_per_case: int = 4000,
        pose_copies: int = 1,
        rounds: int = 2,
        smoothness: tuple = (0.25, 0.5, 1.0, 2.0),
        shape_weight: tuple = (0.0, 0.1, 0.3, 1.0),
        foreground_bias: tuple = (0.0, 0.2, 0.4, 0.6),
        validation_fraction: float = 0.25,
        auto_context: bool = True,
        n_atlases: int = 0,
        atlas_patches: bool = False,
        random_state=None,
        n_jobs: int = 1,
    ):
        self.band_mm = band_mm
        self.jitter_mm = jitter_mm
        self.spacing_ratio = spacing_ratio
        self.classifier = classifier
        self.n_estimators = n_estimators
        self.n_iterations = n_iterations
        self.rows_per_case = rows_per_case
        self.pose_copies = pose_copies
        self.rounds = rounds
        self.smoothness = smoothness
        self.shape_weight = shape_weight
        self.foreground_bias = foreground_bias
        self.validation_fraction = validation_fraction
        self.auto_context = auto_context
        self.n_atlases = n_atlases
        self.atlas_patches = atlas_patches
        self.random_state = random_state
        self.n_jobs = n_jobs

    # -- training ---------------------------------------------------------------------------

    def fit(
        self,
        frame: ShapeFrame,
        template_labels: sitk.Image,
        template_landmarks: np.ndarray,
        images,
        label_maps,
        landmarks,
        groups=None,
    ) -> BoundaryStage:
        """Learn the classifier and choose the cut's weights on training cases.

        ``label_maps`` hold the label values to learn (:func:`medseg.io.label_values`), in the
        images' geometry; ``landmarks`` are the training landmarks (S, N, 3) in mm;
        ``groups`` (S,) their subjects (each case its own by default).
        """
        if not (np.isfinite(self.band_mm) and self.band_mm > 0):
            raise ParameterError(f"`band_mm` must be > 0; got {self.band_mm}")
        if not (np.isfinite(self.spacing_ratio) and self.spacing_ratio > 0):
            raise ParameterError(f"`spacing_ratio` must be > 0; got {self.spacing_ratio}")
        frame = self._grid(frame)
        if not 0 < self.validation_fraction < 1:
            raise ParameterError("`validation_fraction` must be in (0, 1)")
        if int(self.n_atlases) < 0:
            raise ParameterError(f"`n_atlases` must be >= 0; got {self.n_atlases}")
        if int(self.pose_copies) < 0:
            raise ParameterError(f"`pose_copies` must be >= 0; got {self.pose_copies}")
        if int(self.rounds) < 1:
            raise ParameterError(f"`rounds` must be >= 1; got {self.rounds}")
        rng = check_random_state(self.random_state)
        n = len(images)
        groups = np.arange(n) if groups is None else np.asarray(groups)
        if groups.shape != (n,):
            raise ParameterError(f"`groups` must hold one subject per case ({n})")
        self.atlases_ = None
        if int(self.n_atlases) > 0:
            sources = np.sort(rng.permutation(n)[: int(self.n_atlases)])
            self.atlases_ = FrameAtlases.build(
                frame,
                label_maps,
                landmarks,
                template_values(template_labels),
                sources,
                images=images if self.atlas_patches else None,
            )
        cases = []
        for i, (image, label_map, points) in enumerate(
            zip(images, label_maps, landmarks, strict=True)
        ):
            view = (frame, template_labels, template_landmarks)
            use = None
            if self.atlases_ is not None:  # never the case's own subject
                use = groups[self.atlases_.sources] != groups[i]
            points = np.asarray(points, dtype=float)
            case = [self._training_case(*view, image, label_map, points, rng, use)]
            for _ in range(int(self.pose_copies)):
                case.append(self._posed_case(*view, image, label_map, points, rng, use))
            cases.append(case)
        self.values_ = cases[0][0][0].values
        self.context_ = None
        if self.auto_context:
            cases = self._with_context(cases, rng)
        order = rng.permutation(n)
        n_val = min(max(1, int(round(self.validation_fraction * n))), n - 1)
        held, kept = order[:n_val], order[n_val:]
        classifier = self._classifier(rng).fit(*self._rows(cases, kept, rng))
        self.selection_, signals = self._select(cases, held, classifier)
        *chosen, _ = max(self.selection_, key=lambda r: r[3])
        self.smoothness_, self.shape_weight_, self.foreground_bias_ = chosen
        self.reference_ = np.asarray(signals[tuple(chosen)])
        self.classifier_ = self._classifier(rng).fit(*self._rows(cases, range(n), rng))
        return self

    def _grid(self, frame: ShapeFrame) -> ShapeFrame:
        """``frame`` on the stage's grid (:attr:`spacing_ratio` of its spacing)."""
        return replace(frame, spacing=frame.spacing * float(self.spacing_ratio))

    def _with_context(self, cases, rng) -> list:
        """The cases with auto-context features from a first classifier that did not see
        them (two halves, each predicted by the other's); ``context_`` fitted on all."""
        halves = np.array_split(rng.permutation(len(cases)), 2)
        extended = list(cases)
        for part, other in ((halves[0], halves[1]), (halves[1], halves[0])):
            first = self._classifier(rng).fit(*self._rows(cases, part, rng))
            for i in other:
                extended[i] = [
                    (
                        view,
                        truth,
                        nodes,
                        _Joined(features, self._context(first, view, nodes, features)),
                    )
                    for view, truth, nodes, features in cases[i]
                ]
        self.context_ = self._classifier(rng).fit(*self._rows(cases, range(len(cases)), rng))
        return extended

    def _extend(self, first, view: FrameView, nodes, features: np.ndarray) -> np.ndarray:
        return np.hstack([features, self._context(first, view, nodes, features)])

    def _context(self, first, view: FrameView, nodes, features: np.ndarray) -> np.ndarray:
        """:func:`context_features` of ``first``'s answer on ``features``."""
        spacing = np.asarray(view.upright.GetSpacing(), dtype=float)[::-1]
        return context_features(self._probabilities(first, features), nodes, spacing)

    def _training_case(
        self,
        frame,
        template_labels,
        template_landmarks,
        image,
        label_map,
        points,
        rng,
        use,
        moved: Similarity | None = None,
    ):
        """One training image through jittered landmarks: its view, truth and features.

        ``moved`` maps ``label_map``'s mm onto ``image``'s when the image is a posed copy
        (:meth:`_posed_case`): the truth then comes from the original labels in one step.
        """
        noise = rng.normal(scale=self.jitter_mm, size=points.shape)
        noise += rng.normal(scale=self.jitter_mm, size=3)
        view = frame_view(
            frame,
            template_labels,
            template_landmarks,
            image,
            points + noise,
            atlases=self.atlases_,
            use=use,
            reach_mm=self._reach(frame),
        )
        pose = view.pose if moved is None else view.pose.compose(moved)
        truth = sitk.GetArrayFromImage(frame.resample(label_map, pose, is_label=True))
        truth = np.where(np.isin(truth, view.values), truth, 0)
        nodes = self._nodes(view)
        return view, truth, nodes, self._features(view, nodes)

    def _posed_case(
        self, frame, template_labels, template_landmarks, image, label_map, points, rng, use
    ):
        """:meth:`_training_case` of a copy of the image in a random pose, size and field of
        view (:func:`medseg.io.random_pose`)."""
        image, rotation, scale, offset = random_pose(
            image,
            points.mean(axis=0),
            max_angle_deg=_POSE_ANGLE_DEG,
            scale_range=_POSE_SCALES,
            pad_mm=_POSE_PAD_MM,
            random_state=rng,
        )
        moved = Similarity(rotation=rotation, scale=scale, translation=offset)
        return self._training_case(
            frame,
            template_labels,
            template_landmarks,
            image,
            label_map,
            moved(points),
            rng,
            use,
            moved=moved,
        )

    @staticmethod
    def _features(view: FrameView, nodes: np.ndarray) -> np.ndarray:
        """:func:`voxel_features`, and with atlases their vote at each voxel."""
        features = voxel_features(view.upright, view.distances, nodes)
        if view.atlas is None:
            return features
        return np.hstack([features, view.atlas[:, nodes].T.astype(np.float32)])

    def _reach(self, frame: ShapeFrame) -> float:
        """How far outside the shape (mm) the stage reads the signed distances: the band and
        the layer of voxels around it (:meth:`_nodes`), and the contrast's ring."""
        return max(float(self.band_mm), CONTRAST_RING_MM[1]) + frame.spacing

    def _nodes(self, view: FrameView) -> np.ndarray:
        """The domain and one layer of voxels around it (held to background)."""
        return ndimage.binary_dilation(view.domain(self.band_mm))

    def _classifier(self, rng) -> VoxelClassifier:
        boosting = self.classifier == "boosting"
        return VoxelClassifier(
            self.classifier,
            n_estimators=self.n_iterations if boosting else self.n_estimators,
            random_state=rng.randint(np.iinfo(np.int32).max),
            n_jobs=self.n_jobs,
        )

    def _rows(self, cases, which, rng):
        """Rows of the cases ``which``: ``rows_per_case`` each, shared by its images."""
        X, y = [], []
        for i in which:
            share = max(1, int(self.rows_per_case) // len(cases[i]))
            for _, truth, nodes, features in cases[i]:
                take = rng.permutation(len(features))[:share]
                X.append(features[take])
                y.append(truth[nodes][take])
        return np.vstack(X), np.concatenate(y)

    def _select(self, cases, held, classifier) -> tuple[list, dict]:
        """The validation score of the candidates tried, and the cases' :func:`_signals`.

        Coordinate-wise: every pair of weights at the first background cost, every cost at
        the best pair, then every pair again at the best cost.
        """
        held = [
            (cases[i][0], self._probabilities(classifier, np.asarray(cases[i][0][3]))) for i in held
        ]
        scores: dict[tuple, float] = {}
        signals: dict[tuple, list] = {}

        def score(candidates) -> tuple:
            for key in candidates:
                if key in scores:
                    continue
                smooth, weight, bias = key

                def judged(case, smooth=smooth, weight=weight, bias=bias):
                    (view, truth, nodes, _), probabilities = case
                    cut = _cut(
                        view,
                        probabilities,
                        nodes,
                        band_mm=self.band_mm,
                        smoothness=smooth,
                        shape_weight=weight,
                        foreground_bias=bias,
                    )
                    return (
                        _dice_scores(cut, truth, view.values),
                        _signals(view, probabilities, nodes, cut),
                    )

                # the cases' cuts on n_jobs threads (max-flow and sparse algebra drop the GIL)
                values, said = zip(*thread_map(judged, held, self.n_jobs), strict=True)
                scores[key], signals[key] = float(np.mean(values)), list(said)
            return max(scores, key=scores.get)

        pairs = [(float(s), float(w)) for s, w in product(self.smoothness, self.shape_weight)]
        biases = [float(b) for b in self.foreground_bias]
        best = score([(s, w, biases[0]) for s, w in pairs])
        best = score([(*best[:2], b) for b in biases])
        score([(s, w, best[2]) for s, w in pairs])
        return [(*key, value) for key, value in scores.items()], signals

    def _probabilities(self, classifier: VoxelClassifier, features: np.ndarray) -> np.ndarray:
        """(n, 1 + K) probabilities in the order background, ``values_`` (0 if unseen)."""
        classifier.n_jobs = self.n_jobs  # its threads (a loaded classifier has one)
        proba = classifier.predict_proba(features)
        out = np.zeros((len(features), 1 + len(self.values_)))
        for column, value in enumerate((0,) + tuple(self.values_)):
            hit = np.flatnonzero(classifier.classes_ == value)
            if hit.size:
                out[:, column] = proba[:, hit[0]]
        return out

    # -- inference --------------------------------------------------------------------------

    def refine(
        self,
        frame: ShapeFrame,
        template_labels: sitk.Image,
        template_landmarks: np.ndarray,
        image: sitk.Image,
        landmarks: np.ndarray,
    ) -> Refined:
        """The refined label map of ``image`` (its grid, uint8, the label values), and how
        far image and shape agreed (:class:`Refined`)."""
        frame = self._grid(frame)
        view, labels, signals = self._round(
            frame, template_labels, template_landmarks, image, landmarks
        )
        first = signals
        for _ in range(1, int(self.rounds)):
            moved = _follow(view, labels, landmarks)
            if moved is None:
                break
            try:
                again = self._round(frame, template_labels, template_landmarks, image, moved)
            except ImageGeometryError:  # landmarks that collapsed onto one another
                break
            if not again[1].any() or self._score(*again[2]) > self._score(*signals):
                break
            view, labels, signals = again
            landmarks = moved
        return Refined(
            label=to_input(view, labels, image),
            disagreement=first[0],
            change=first[1],
            score=self._score(*first),
        )

    def _round(self, frame, template_labels, template_landmarks, image, landmarks):
        """One pass: the view from ``landmarks``, the cut's labels on its grid, its signals."""
        view = frame_view(
            frame,
            template_labels,
            template_landmarks,
            image,
            landmarks,
            atlases=self.atlases_,
            reach_mm=self._reach(frame),
        )
        nodes = self._nodes(view)
        features = self._features(view, nodes)
        if self.context_ is not None:
            features = self._extend(self.context_, view, nodes, features)
        probabilities = self._probabilities(self.classifier_, features)
        labels = _cut(
            view,
            probabilities,
            nodes,
            band_mm=self.band_mm,
            smoothness=self.smoothness_,
            shape_weight=self.shape_weight_,
            foreground_bias=self.foreground_bias_,
        )
        return view, labels, _signals(view, probabilities, nodes, labels)

    def _score(self, disagreement: float, change: float) -> float:
        """NaN with fewer than :data:`MIN_REFERENCE_CASES` validation cases to compare with."""
        reference = np.asarray(self.reference_, dtype=float)
        if len(reference) < MIN_REFERENCE_CASES:
            return float("nan")
        centre = reference.mean(axis=0)
        spread = np.maximum(reference.std(axis=0), _MIN_SPREAD)
        return float(np.max((np.array([disagreement, change]) - centre) / spread))

    # -- persistence ------------------------------------------------------------------------

    FORMAT = "medseg.segmenter.BoundaryStage"
    # 2: atlases (atlases.npz, their features); 3: a boosting classifier; 4: a grid finer or
    # coarser than the frame's (spacing_ratio); 5: a background cost (foreground_bias);
    # 1 to 4 still load
    FORMAT_VERSION = 5
    _PARAMS = (
        "band_mm",
        "jitter_mm",
        "n_estimators",
        "rows_per_case",
        "pose_copies",
        "rounds",
        "validation_fraction",
        "auto_context",
    )

    def save(self, folder) -> Path:
        """Write ``stage.npz`` (weights, label values, selection) and ``classifier.npz``."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        header = {
            "format": self.FORMAT,
            "format_version": self._written_version(),
            "params": {name: getattr(self, name) for name in self._PARAMS}
            | {
                "classifier": self.classifier_.method,
                "n_iterations": self.n_iterations,
                "spacing_ratio": float(self.spacing_ratio),
            },
            "values": [int(v) for v in self.values_],
            "smoothness": float(self.smoothness_),
            "shape_weight": float(self.shape_weight_),
            "foreground_bias": float(self.foreground_bias_),
            "n_atlases": 0 if self.atlases_ is None else len(self.atlases_),
            "atlas_patches": self.atlases_ is not None and self.atlases_.images is not None,
        }
        arrays = {"selection": np.asarray(self.selection_), "reference": self.reference_}
        save_arrays(folder / "stage.npz", arrays, header=header)
        if self.atlases_ is not None:
            save_arrays(
                folder / "atlases.npz",
                self.atlases_.arrays(),
                header={"format": FrameAtlases.FORMAT, "format_version": FrameAtlases.VERSION},
            )
        self.classifier_.save(folder / "classifier.npz")
        if self.context_ is not None:
            self.context_.save(folder / "context.npz")
        return folder

    def _written_version(self) -> int:
        """The oldest format that holds this stage, so that older medseg reads what it can
        (a forest without atlases on the frame's grid is what version 1 was) and refuses
        what it would misread."""
        if float(self.foreground_bias_) != 0.0:
            return 5
        if float(self.spacing_ratio) != 1.0:
            return 4
        if self.classifier_.method == "boosting":
            return 3
        return 1 if self.atlases_ is None else 2

    @classmethod
    def load(cls, folder) -> BoundaryStage:
        """Read a stage written by :meth:`save`; ``ModelFileError`` if it is not one."""
        folder = Path(folder)
        header, arrays = load_arrays(folder / "stage.npz", what="boundary stage")
        source = str(folder / "stage.npz")
        check_format(header, format=cls.FORMAT, version=cls.FORMAT_VERSION, source=source)
        try:
            # stages before copies had none; before rounds, one pass
            params = {"pose_copies": 0, "rounds": 1} | header["params"]
            stage = cls(**{name: params[name] for name in cls._PARAMS})
            stage.values_ = tuple(int(v) for v in header["values"])
            stage.smoothness_ = float(header["smoothness"])
            stage.shape_weight_ = float(header["shape_weight"])
            # stages before version 5 cut without a background cost
            stage.foreground_bias_ = float(header.get("foreground_bias", 0.0))
            stage.selection_ = [tuple(map(float, row)) for row in arrays["selection"]]
            stage.reference_ = np.asarray(arrays["reference"], dtype=float)
            stage.n_atlases = int(header.get("n_atlases", 0))  # stages before atlases: 0
            stage.atlas_patches = bool(header.get("atlas_patches", False))
            stage.n_iterations = int(header["params"].get("n_iterations", stage.n_iterations))
            # stages before version 4 worked on the frame's own grid
            stage.spacing_ratio = float(header["params"].get("spacing_ratio", 1.0))
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{source} is incomplete or corrupt: {exc}") from None
        if not stage.values_ or min(stage.values_) < 1 or max(stage.values_) > 255:
            raise ModelFileError(f"{source}: label values {stage.values_}")
        if not (np.isfinite(stage.spacing_ratio) and stage.spacing_ratio > 0):
            raise ModelFileError(f"{source}: grid spacing ratio {stage.spacing_ratio}")
        if not np.isfinite(stage.foreground_bias_):
            raise ModelFileError(f"{source}: background cost {stage.foreground_bias_}")
        reference = stage.reference_
        if reference.ndim != 2 or reference.shape[1] != 2 or not np.isfinite(reference).all():
            raise ModelFileError(f"{source}: reference signals of shape {reference.shape}")
        stage.atlases_ = None
        if stage.n_atlases:
            stage.atlases_ = _load_atlases(folder / "atlases.npz", stage)
        stage.classifier_ = VoxelClassifier.load(folder / "classifier.npz")
        stage.classifier = stage.classifier_.method  # stages before version 3: "forest"
        stage.context_ = None
        if stage.auto_context:
            if not (folder / "context.npz").is_file():
                raise ModelFileError(
                    f"{folder / 'context.npz'} is missing; the model is incomplete"
                )
            stage.context_ = VoxelClassifier.load(folder / "context.npz")
        known = set(int(c) for c in stage.classifier_.classes_)
        if not known <= {0, *stage.values_}:
            raise ModelFileError(
                f"{folder / 'classifier.npz'} predicts labels {sorted(known)}, not those of "
                f"stage.npz {stage.values_}"
            )
        return stage


def _load_atlases(path: Path, stage: BoundaryStage) -> FrameAtlases:
    """The stage's atlases; ``ModelFileError`` if missing or not the stage's."""
    if not path.is_file():
        raise ModelFileError(f"{path} is missing; the model is incomplete")
    header, arrays = load_arrays(path, what="frame atlases")
    check_format(header, format=FrameAtlases.FORMAT, version=FrameAtlases.VERSION, source=str(path))
    try:
        atlases = FrameAtlases.from_arrays(arrays)
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelFileError(f"{path} is incomplete or corrupt: {exc}") from None
    shares, points = atlases.shares, atlases.landmarks
    if (
        len(atlases) != stage.n_atlases
        or atlases.values != tuple(stage.values_)
        or shares.ndim != 5
        or shares.shape[1] != len(atlases.values)
        or points.ndim != 3
        or len(points) != len(shares)
        or not np.isfinite(points).all()
    ):
        raise ModelFileError(f"{path} does not match its stage.npz")
    return atlases
