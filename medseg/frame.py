"""The shape's own frame: the structure upright, at its mean size, in a training-like box.

The similarity (rotation, uniform scale, translation; never a reflection) that takes a
configuration of landmarks onto the model's reference shape defines a frame free of the
image's pose: resampled into it, every image shows the structure as the training
population does on average, and only as much of its surroundings as a training image did.
The frame comes from landmarks the pose-free MRF found, so whatever is computed in it stays
pose free: a second detection pass (:class:`medseg.ShapePriorSegmenter`, ``frame_passes``)
and, later, appearance models that need not be rotation invariant.

At training time each image is placed in the frame by its own landmarks; :meth:`ShapeFrame.fit`
learns the reference shape (the Procrustes mean, in mm) and the box: along each axis of the
frame and each way, the median over the training images of how far their field of view
reaches from the structure's centre, so that a resampled image covers what a training image
covered (its intensity statistics, which the detectors normalise by, and the filters' view
beyond the structure then do not depend on the field of view a user's image has).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from numpy.typing import ArrayLike

from medseg.errors import ModelFileError, ParameterError
from medseg.geometry import Similarity, procrustes_mean, similarity_fit
from medseg.io import check_format, load_arrays, resample_affine, save_arrays

__all__ = ["ShapeFrame"]


def _reach(image: sitk.Image, pose: Similarity, centre: np.ndarray) -> np.ndarray:
    """How far the field of view of ``image`` reaches from ``centre`` (frame mm) along the
    frame's axes, backwards and forwards: a (2, 3) array of distances in frame mm.

    Along rays rather than by the corners, so that an image turned in the frame does not
    count the corners of its bounding box, which it does not cover.
    """
    size = np.asarray(image.GetSize(), dtype=float)
    start = np.asarray(image.TransformPhysicalPointToContinuousIndex(
        pose.inverse(centre[None])[0].tolist()))  # fmt: skip
    out = np.zeros((2, 3))
    for axis in range(3):
        for side, sign in enumerate((-1.0, 1.0)):
            step_mm = pose.inverse((centre + sign * np.eye(3)[axis])[None])[0]
            step = np.asarray(image.TransformPhysicalPointToContinuousIndex(step_mm.tolist()))
            step -= start  # index change per frame mm along the ray
            with np.errstate(divide="ignore", invalid="ignore"):
                to_low = np.where(step < 0, (-0.5 - start) / step, np.inf)
                to_high = np.where(step > 0, (size - 0.5 - start) / step, np.inf)
            out[side, axis] = max(0.0, float(np.min(np.minimum(to_low, to_high))))
    return out


@dataclass(frozen=True)
class ShapeFrame:
    """The reference shape and the box of the frame, in the frame's own mm coordinates.

    Attributes
    ----------
    reference : (N, 3) float array, mm
        The reference configuration (Procrustes mean of the training landmarks: centred at
        the origin, in the orientation of the first training shape, mean centroid size).
    lower, upper : (3,) float arrays, mm
        The box, in frame coordinates (x, y, z).
    spacing : float, mm
        Voxel size of the frame's grid (isotropic).
    """

    reference: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    spacing: float

    FORMAT = "medseg.frame.ShapeFrame"
    FORMAT_VERSION = 1

    @classmethod
    def fit(cls, shapes: ArrayLike, images) -> ShapeFrame:
        """Learn the frame from training landmarks and their images.

        Parameters
        ----------
        shapes : (S, N, 3) float array, mm
            Landmarks in correspondence, each in its own image's physical space.
        images : sequence of S 3D SimpleITK images
        """
        shapes = np.asarray(shapes, dtype=float)
        if shapes.ndim != 3 or shapes.shape[2] != 3 or len(shapes) != len(images):
            raise ParameterError(
                f"`shapes` must be (S, N, 3) with one image each; got {shapes.shape} and "
                f"{len(images)} images"
            )
        reference = procrustes_mean(shapes)
        centre = reference.mean(axis=0)
        reach, spacings = [], []
        for points, image in zip(shapes, images, strict=True):
            pose = similarity_fit(points, reference)
            reach.append(_reach(image, pose, centre))
            spacings.append(min(image.GetSpacing()))
        lower, upper = np.median(reach, axis=0)
        return cls(
            reference=reference,
            lower=centre - lower,
            upper=centre + upper,
            spacing=float(np.median(spacings)),
        )

    # -- the frame of one image -------------------------------------------------------------

    def pose(self, landmarks: ArrayLike) -> Similarity:
        """The similarity taking ``landmarks`` (an image's mm) into the frame."""
        landmarks = np.asarray(landmarks, dtype=float)
        if landmarks.shape != self.reference.shape:
            raise ParameterError(
                f"`landmarks` must be {self.reference.shape}, got {landmarks.shape}"
            )
        return similarity_fit(landmarks, self.reference)

    def turn_deg(self, landmarks: ArrayLike, other: ArrayLike) -> float:
        """The angle (degrees, 0-180) of the rotation between the frames of two
        configurations in one image: how far ``other`` is the shape turned from
        ``landmarks``, whatever their sizes and positions."""
        relative = self.pose(landmarks).rotation @ self.pose(other).rotation.T
        cosine = (np.trace(relative) - 1.0) / 2.0
        return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))

    def grid(self) -> sitk.Image:
        """An empty image on the frame's grid (identity direction, frame mm)."""
        size = np.maximum(np.ceil((self.upper - self.lower) / self.spacing), 1).astype(int)
        grid = sitk.Image([int(s) for s in size], sitk.sitkUInt8)
        grid.SetSpacing([self.spacing] * 3)
        grid.SetOrigin((self.lower + 0.5 * self.spacing).tolist())
        return grid

    def resample(
        self, image: sitk.Image, pose: Similarity, *, is_label: bool = False
    ) -> sitk.Image:
        """``image`` seen in the frame defined by ``pose`` (:meth:`pose`), on :meth:`grid`.

        Linear interpolation (nearest neighbour for a label map); outside the image, the
        median of its border voxels (0 for a label map), as if the field of view went on.
        """
        matrix = pose.scale * pose.rotation
        return resample_affine(image, matrix, pose.translation, self.grid(), is_label=is_label)

    # -- persistence ------------------------------------------------------------------------

    def save(self, path) -> Path:
        """Write the frame to one ``.npz`` file (:func:`medseg.io.save_arrays`)."""
        arrays = {
            "reference": self.reference,
            "lower": self.lower,
            "upper": self.upper,
            "spacing": np.array(self.spacing),
        }
        header = {"format": self.FORMAT, "format_version": self.FORMAT_VERSION}
        return save_arrays(path, arrays, header=header)

    @classmethod
    def load(cls, path) -> ShapeFrame:
        """Read a frame written by :meth:`save`; ``ModelFileError`` if the file is not one."""
        header, arrays = load_arrays(path, what="shape frame")
        check_format(header, format=cls.FORMAT, version=cls.FORMAT_VERSION, source=str(path))
        try:
            reference = np.asarray(arrays["reference"], dtype=float)
            lower = np.asarray(arrays["lower"], dtype=float)
            upper = np.asarray(arrays["upper"], dtype=float)
            spacing = float(arrays["spacing"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{path} is incomplete or corrupt ({exc})") from None
        if (
            reference.ndim != 2
            or reference.shape[1] != 3
            or lower.shape != (3,)
            or upper.shape != (3,)
            or not np.all(upper > lower)
            or not spacing > 0
            or not np.isfinite(reference).all()
        ):
            raise ModelFileError(f"{path}: shape frame arrays of inconsistent shapes or values")
        return cls(reference=reference, lower=lower, upper=upper, spacing=spacing)
