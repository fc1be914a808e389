"""A second look in the shape's own frame: the same pipeline on the image made upright.

The first pass finds the landmarks in the image as it is, with no initialisation. Their
similarity onto the model's reference shape (:class:`medseg.frame.ShapeFrame`) resamples the
image so that the structure is upright, at its mean size, in a training-like field of view;
the detectors, the handedness term and the active shape search then run on that view, and
what they find is mapped back. Nothing in it depends on the input's pose, field of view or
scale beyond what the first pass got right: the frame comes from the pose-free MRF solution.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import SimpleITK as sitk

from medseg.segmenter._result import Hypothesis, Located

__all__ = ["in_frame_passes"]


def _back(found: Located, pose, image: sitk.Image) -> Located:
    """``found`` (in frame mm) mapped into ``image``'s physical space."""
    back = pose.inverse
    return replace(
        found,
        candidates=found.candidates.mapped(back, image),
        chosen=back(found.chosen),
        landmarks=back(found.landmarks),
        hypotheses=[
            Hypothesis(h.labels, back(h.chosen), back(h.landmarks), h.profile_cost)
            for h in found.hypotheses
        ],
        frame_pose=pose,
    )


def in_frame_passes(
    model, image: sitk.Image, first: Located, *, n_passes: int, locate: Callable
) -> Located:
    """Run ``locate`` ``n_passes`` times in the frame of the previous pass's landmarks.

    Parameters
    ----------
    model : ShapePriorSegmenter
        Fitted, with a ``frame_``.
    image : SimpleITK image
        The input.
    first : Located
        The first pass, in the input's space.
    n_passes : int
    locate : callable
        ``locate(image) -> Located``: one pass of the model's pipeline.

    Returns
    -------
    Located
        The last pass, mapped back into the input's space; its timings add up all passes.
    """
    found = first
    timings = dict(first.timings)
    for _ in range(int(n_passes)):
        t0 = time.perf_counter()
        pose = model.frame_.pose(found.landmarks)
        upright = model.frame_.resample(image, pose)
        timings["frame"] = timings.get("frame", 0.0) + time.perf_counter() - t0
        inner = locate(upright)
        for key, seconds in inner.timings.items():
            timings[key] = timings.get(key, 0.0) + seconds
        found = _back(inner, pose, image)
    found.timings = timings
    return found
