"""Training label maps in the shape's frame, fused onto new landmarks by thin-plate splines.

One template carried onto perfect landmarks stops at about 0.90 Dice on the hippocampus:
it is one subject's anatomy. Several training label maps, each carried by its own
thin-plate spline from its landmarks onto the same landmarks and averaged, represent the
structure better (0.93 with 10-20 of them on the same cases): where subjects differ
between the landmarks, the vote says how much. Here the atlases live in the shape's frame
(:class:`medseg.frame.ShapeFrame`), each resampled there by its own landmarks' similarity, so
all share one grid; a new case's landmarks in the frame are the control points of every
spline, and the splines to all atlases are one solve with several right-hand sides.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
from scipy import ndimage
from scipy.interpolate import RBFInterpolator

from medseg.frame import ShapeFrame

__all__ = ["FrameAtlases"]

_LEVELS = 255  # indicators are stored as uint8 shares of this
_MARGIN_MM = 5.0  # the fused region: the atlases' support and this much around it
_SSD_FLOOR = 1e-3  # added to the smallest patch distance (normalised units): identical patches


@dataclass
class FrameAtlases:
    """Soft label maps of some training cases on the frame's grid, with their landmarks.

    Attributes
    ----------
    shares : (A, K, Z, Y, X) uint8 array
        Per atlas, each label's indicator linearly resampled into the frame, times 255.
    landmarks : (A, N, 3) float array
        The atlases' landmarks in frame mm.
    values : tuple of int
        The K label values.
    sources : (A,) int array
        Which training cases they are (their order in the fit).
    images : (A, Z, Y, X) float16 array or None
        Their images in the frame, normalised (:func:`_normalised`): with them, each
        atlas' vote at a voxel is weighted by how alike the two images look around it.
    """

    shares: np.ndarray
    landmarks: np.ndarray
    values: tuple
    sources: np.ndarray
    images: np.ndarray | None = None

    FORMAT = "medseg.segmenter.FrameAtlases"  # the header of ``atlases.npz``
    VERSION = 1

    @classmethod
    def build(
        cls, frame: ShapeFrame, label_maps, landmarks, values, sources, images=None
    ) -> FrameAtlases:
        """The training cases ``sources`` (indices into ``label_maps`` / ``landmarks``, and
        ``images`` for votes weighted by patch similarity)."""
        shares, points, upright = [], [], []
        for i in sources:
            pose = frame.pose(landmarks[i])
            if images is not None:
                upright.append(sitk.GetArrayFromImage(frame.resample(images[i], pose)))
            array = sitk.GetArrayViewFromImage(label_maps[i])
            own = []
            for value in values:
                indicator = sitk.GetImageFromArray((array == value).astype(np.float32))
                indicator.CopyInformation(label_maps[i])
                moved = sitk.GetArrayFromImage(frame.resample(indicator, pose))
                own.append(np.rint(np.clip(moved, 0.0, 1.0) * _LEVELS).astype(np.uint8))
            shares.append(np.stack(own))
            points.append(pose(np.asarray(landmarks[i], dtype=float)))
        atlases = cls(
            shares=np.stack(shares),
            landmarks=np.stack(points),
            values=tuple(int(v) for v in values),
            sources=np.asarray(sources, dtype=np.intp),
        )
        if images is not None:
            region = atlases._region(np.arange(len(atlases)), frame.spacing)
            atlases.images = np.stack([_normalised(a, region) for a in upright]).astype(np.float16)
        return atlases

    def __len__(self) -> int:
        return len(self.shares)

    def fuse(
        self, grid: sitk.Image, landmarks: np.ndarray, *, use: np.ndarray | None = None
    ) -> np.ndarray:
        """(1 + K, Z, Y, X) float32 label probabilities on ``grid`` (the frame's image of the
        case), background first: the vote of the atlases ``use`` (bool mask; all by
        default) carried onto ``landmarks`` (frame mm) by their thin-plate splines; with
        atlas images, each vote weighted by patch similarity (Coupe et al. 2011: weights
        ``exp(-SSD / min SSD)`` over 3x3x3 patches)."""
        use = np.ones(len(self), dtype=bool) if use is None else np.asarray(use, dtype=bool)
        chosen = np.flatnonzero(use)
        size = self.shares.shape[2:]
        out = np.zeros((1 + len(self.values), *size), dtype=np.float32)
        if chosen.size == 0:
            out[0] = 1.0
            return out
        spacing = np.asarray(grid.GetSpacing(), dtype=float)  # isotropic, identity direction
        origin = np.asarray(grid.GetOrigin(), dtype=float)
        region = self._region(chosen, spacing[0])
        lo = np.array([r.start for r in region])
        hi = np.array([r.stop for r in region])
        zyx = np.mgrid[region].reshape(3, -1).T
        points = origin + zyx[:, ::-1] * spacing  # (x, y, z) frame mm
        landmarks = np.asarray(landmarks, dtype=float)
        moves = (self.landmarks[chosen] - landmarks).transpose(1, 0, 2).reshape(len(landmarks), -1)
        # Every spline has the same control points: one solve for all atlases.
        spline = RBFInterpolator(landmarks, moves, kernel="linear", degree=1)
        pulled = (points[:, None, :] + spline(points).reshape(len(points), -1, 3)) - origin
        pulled = pulled / spacing  # continuous (x, y, z) indices of each atlas' grid
        votes = np.zeros((len(chosen), len(self.values), len(points)), dtype=np.float32)
        for column, atlas in enumerate(chosen):
            coords = pulled[:, column, ::-1].T
            for k in range(len(self.values)):
                votes[column, k] = ndimage.map_coordinates(
                    self.shares[atlas, k].astype(np.float32), coords, order=1, cval=0.0
                )
        votes /= _LEVELS
        if self.images is None:
            weights = np.full((len(chosen), len(points)), 1.0 / len(chosen), dtype=np.float32)
        else:
            weights = self._patch_weights(grid, region, chosen, pulled)
        total = np.einsum("akn,an->kn", votes, weights)
        out[(slice(1, None), *region)] = total.reshape(len(self.values), *(hi - lo))
        out[0] = np.clip(1.0 - out[1:].sum(axis=0), 0.0, 1.0)
        return out

    def _patch_weights(self, grid, region, chosen, pulled) -> np.ndarray:
        """(A, n) weights of each atlas' vote at the region's voxels, summing to one."""
        shape = tuple(r.stop - r.start for r in region)
        case = _normalised(sitk.GetArrayFromImage(grid).astype(np.float32), region)[region]
        ssd = np.empty((len(chosen), case.size), dtype=np.float32)
        for column, atlas in enumerate(chosen):
            coords = pulled[:, column, ::-1].T
            seen = ndimage.map_coordinates(self.images[atlas].astype(np.float32), coords, order=1)
            diff = (seen.reshape(shape) - case) ** 2
            ssd[column] = ndimage.uniform_filter(diff, size=3, mode="nearest").ravel()
        scale = ssd.min(axis=0) + _SSD_FLOOR
        weights = np.exp(-(ssd - ssd.min(axis=0)) / scale)
        return weights / weights.sum(axis=0)

    def _region(self, chosen: np.ndarray, spacing: float) -> tuple[slice, slice, slice]:
        """The grid box (zyx slices) of the atlases' support and a margin around it."""
        support = self.shares[chosen].any(axis=(0, 1))
        size = np.asarray(support.shape)
        if not support.any():
            return tuple(slice(0, int(n)) for n in size)
        found = np.argwhere(support)
        pad = int(np.ceil(_MARGIN_MM / spacing))
        lo = np.clip(found.min(axis=0) - pad, 0, size)
        hi = np.clip(found.max(axis=0) + pad + 1, 0, size)
        return tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))

    def labels(self, probabilities: np.ndarray) -> np.ndarray:
        """The fused label map (values, uint8): inside where background is under one half,
        each voxel there the label with the largest share (as :func:`warp_labels`)."""
        inside = probabilities[0] < 0.5
        out = np.zeros(probabilities.shape[1:], dtype=np.uint8)
        pick = np.argmax(probabilities[1:], axis=0)
        out[inside] = np.asarray(self.values, dtype=np.uint8)[pick[inside]]
        return out

    # -- persistence ------------------------------------------------------------------------

    def arrays(self) -> dict:
        out = {
            "shares": self.shares,
            "landmarks": self.landmarks,
            "values": np.asarray(self.values, dtype=np.int64),
            "sources": self.sources,
        }
        if self.images is not None:
            out["images"] = self.images
        return out

    @classmethod
    def from_arrays(cls, arrays) -> FrameAtlases:
        images = arrays["images"] if "images" in arrays else None
        return cls(
            shares=np.asarray(arrays["shares"], dtype=np.uint8),
            landmarks=np.asarray(arrays["landmarks"], dtype=float),
            values=tuple(int(v) for v in arrays["values"]),
            sources=np.asarray(arrays["sources"], dtype=np.intp),
            images=None if images is None else np.asarray(images, dtype=np.float16),
        )


def _normalised(array: np.ndarray, region) -> np.ndarray:
    """``array`` centred on its median over ``region`` and scaled by its interquartile
    range there: the frame's box is the same for every case, so this is comparable."""
    values = array[region]
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    return ((array - median) / max(float(q3 - q1), 1e-6)).astype(np.float32)
