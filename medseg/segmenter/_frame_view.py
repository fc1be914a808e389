"""The image seen in the frame of some landmarks, and labels carried back from it.

The regional stage (:mod:`medseg.segmenter._boundary`) works in the shape's own frame
(:class:`medseg.frame.ShapeFrame`): the image resampled so that the landmarks found sit on
the reference shape, and the template's labels warped onto them there, with their signed
distances. What it decides there comes back to the input's exact grid through the signed
distances of the labels, linearly interpolated, which keeps the boundary's sub-voxel
position that nearest-neighbour resampling of the labels would lose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from medseg.frame import ShapeFrame
from medseg.geometry import Similarity
from medseg.io import resample_affine
from medseg.reconstruction import warp_labels
from medseg.segmenter._atlases import FrameAtlases

__all__ = [
    "FrameView",
    "frame_view",
    "mask_box",
    "signed_distance",
    "template_values",
    "to_input",
]

_FAR_MM = 1e3  # the signed distance given where it is not computed (far outside)


def template_values(template_labels: sitk.Image) -> tuple:
    """The template's non-zero label values, ascending."""
    return tuple(int(v) for v in np.unique(sitk.GetArrayViewFromImage(template_labels)) if v)


def signed_distance(mask: np.ndarray, spacing_zyx) -> np.ndarray:
    """Signed distance (mm) to the boundary of ``mask``: negative inside, about +-half a
    voxel on either side of the boundary."""
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return np.full(mask.shape, _FAR_MM, dtype=np.float32)
    half = 0.5 * float(np.min(spacing_zyx))
    outside = ndimage.distance_transform_edt(~mask, sampling=spacing_zyx)
    inside = ndimage.distance_transform_edt(mask, sampling=spacing_zyx)
    return np.where(mask, half - inside, outside - half).astype(np.float32)


def mask_box(mask: np.ndarray, margin: int = 1) -> tuple[slice, ...]:
    """The bounding box of ``mask`` grown by ``margin`` voxels (clipped to the grid).

    With ``margin >= 1``, :func:`signed_distance` of the mask (or of any part of it) computed
    on the box equals the whole grid's there: every voxel of the mask is inside, and the
    nearest voxel outside it is too (moved into the box, an outside voxel only comes
    closer, and the box's rim is outside). The whole grid when ``mask`` is empty.
    """
    index = np.argwhere(mask)
    if not len(index):
        return tuple(slice(0, n) for n in mask.shape)
    lo = np.maximum(index.min(axis=0) - margin, 0)
    hi = np.minimum(index.max(axis=0) + margin + 1, mask.shape)
    return tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))


@dataclass
class FrameView:
    """An image seen in the frame of some landmarks, with the template warped onto them.

    Attributes
    ----------
    pose : Similarity
        The input's mm into the frame's mm.
    upright : SimpleITK image
        The image on the frame's grid.
    shape : (Z, Y, X) uint8 array
        The warped template's labels on that grid.
    distances : (1 + K, Z, Y, X) float32 array, mm
        Signed distances to the union, then to each of the K label values.
    values : tuple of int
        The label values (1 for a single label).
    atlas : (1 + K, Z, Y, X) float32 array or None
        With atlases (:class:`FrameAtlases`), their fused label probabilities (background
        first); ``shape`` is then their vote instead of the one template's warp.
    """

    pose: Similarity
    upright: sitk.Image
    shape: np.ndarray
    distances: np.ndarray
    values: tuple
    atlas: np.ndarray | None = None

    def domain(self, band_mm: float) -> np.ndarray:
        """The voxels the cut decides: within ``band_mm`` outside the union, and inside."""
        return self.distances[0] <= band_mm


def frame_view(
    frame: ShapeFrame,
    template_labels: sitk.Image,
    template_landmarks: np.ndarray,
    image: sitk.Image,
    landmarks: np.ndarray,
    *,
    atlases: FrameAtlases | None = None,
    use: np.ndarray | None = None,
    reach_mm: float = np.inf,
) -> FrameView:
    """``image`` resampled into the frame of ``landmarks``, the template warped there, or
    with ``atlases`` the vote of those ``use`` selects (:meth:`FrameAtlases.fuse`).

    The signed distances are exact wherever the union's is at most ``reach_mm``: they are
    computed in the union's box grown by more than that (:func:`mask_box`), and every voxel
    beyond it is farther; there they are ``_FAR_MM``.
    """
    pose = frame.pose(landmarks)
    upright = frame.resample(image, pose)
    atlas = None
    if atlases is not None:
        atlas = atlases.fuse(upright, pose(landmarks), use=use)
        shape = atlases.labels(atlas)
    else:
        shape = sitk.GetArrayFromImage(
            warp_labels(template_labels, template_landmarks, pose(landmarks), upright)
        )
    values = template_values(template_labels)
    spacing = np.asarray(upright.GetSpacing(), dtype=float)[::-1]
    margin = int(min(np.ceil(reach_mm / spacing.min()) + 1, max(shape.shape)))
    box = mask_box(shape > 0, margin=margin)
    part = shape[box]
    masks = [part > 0] + ([part == v for v in values] if len(values) > 1 else [])
    distances = np.full((1 + len(values), *shape.shape), _FAR_MM, dtype=np.float32)
    for k, mask in enumerate(masks):
        distances[(k, *box)] = signed_distance(mask, spacing)
    if len(values) == 1:  # the one label's distances are the union's
        distances[1] = distances[0]
    return FrameView(pose, upright, shape, distances, values, atlas)


def to_input(view: FrameView, labels: np.ndarray, image: sitk.Image) -> sitk.Image:
    """Frame labels onto ``image``'s grid, through their linearly resampled signed distances.

    The distances are computed in the labels' box (:func:`mask_box`, one voxel beyond it):
    exact there, and beyond it only their sign, positive, matters.
    """
    spacing = np.asarray(view.upright.GetSpacing(), dtype=float)[::-1]
    pose = view.pose  # the frame back to the input: x = R^T (y - t) / s
    matrix = pose.rotation.T / pose.scale
    offset = -(pose.rotation.T @ pose.translation) / pose.scale
    box = mask_box(labels > 0)

    def moved(mask: np.ndarray) -> np.ndarray:
        distances = np.full(mask.shape, _FAR_MM, dtype=np.float32)
        distances[box] = signed_distance(mask[box], spacing)
        field = sitk.GetImageFromArray(distances)
        field.CopyInformation(view.upright)
        out = resample_affine(field, matrix, offset, image, fill="border")
        return sitk.GetArrayFromImage(out)

    union = moved(labels > 0) < 0
    out = np.zeros(union.shape, dtype=np.uint8)
    if len(view.values) == 1:
        out[union] = view.values[0]
    else:
        distance = np.stack([moved(labels == v)[union] for v in view.values])
        out[union] = np.asarray(view.values, dtype=np.uint8)[np.argmin(distance, axis=0)]
    result = sitk.GetImageFromArray(out)
    result.CopyInformation(image)
    return result
