"""The segmenter: the estimator that composes the parts, its results, its model folder.

* :class:`ShapePriorSegmenter`: ``fit(cohort)`` / ``segment(image)`` / ``save`` / ``load``;
* :class:`Segmentation`, :class:`Hypothesis`: what ``segment`` returns;
* :func:`load_model`: read a model folder (checksums and format version verified);
* :func:`segment_bytes`: the estimated peak memory of segmenting one image;
* :class:`BoundaryStage`: the regional stage (voxel classifier and graph cut in the
  shape's frame), on by default, which the ASM baseline shares;
* :class:`FrameAppearance`: the check of the found shape against the training images'
  appearance in the shape's frame, on by default.

This is the one package that wires the parts together: the correspondence step, the
detectors, the prior, the solver and the reconstruction know only arrays and images.
"""

from medseg.segmenter._appearance import FrameAppearance
from medseg.segmenter._boundary import BoundaryStage, Refined
from medseg.segmenter._estimator import (
    MIN_TRAINING_CASES,
    QUALITY_THRESHOLD,
    ShapePriorSegmenter,
    load_model,
)
from medseg.segmenter._memory import segment_bytes
from medseg.segmenter._result import Hypothesis, Segmentation

__all__ = [
    "ShapePriorSegmenter",
    "Segmentation",
    "Hypothesis",
    "load_model",
    "segment_bytes",
    "MIN_TRAINING_CASES",
    "QUALITY_THRESHOLD",
    "BoundaryStage",
    "FrameAppearance",
    "Refined",
]
