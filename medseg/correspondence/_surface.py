"""Boundaries of label maps as triangle meshes in physical mm, and closest points on them.

The first step of the correspondence: each case's structure becomes one closed, outward
oriented surface in its image's world frame (marching cubes on the lightly smoothed mask,
through :func:`medseg.io.voxel_to_physical`), so that nothing downstream sees voxels,
spacings or image directions. The checks here give a bad label map (missing labels, a
structure in several pieces) a message that names its case. The mesh queries at the end
(a PyVista mesh, closest points on its triangles) are what the transfer projects onto.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pyvista as pv
import SimpleITK as sitk
from scipy import ndimage
from skimage.measure import marching_cubes

from medseg.errors import LabelError
from medseg.io import read_image, select_labels, voxel_to_physical


def _case_name(case_id: str | None, index: int | None = None) -> str:
    if case_id is not None:
        return f"case {case_id!r}"
    return f"label map #{index}" if index is not None else "label map"


def _as_label_image(source, name: str) -> sitk.Image:
    image = source if isinstance(source, sitk.Image) else read_image(source)
    if image.GetDimension() != 3:
        raise LabelError(f"{name}: expected a 3D label map, got {image.GetDimension()}D")
    return image


def _single_component(mask: np.ndarray, name: str, keep_largest: bool, min_fraction: float):
    """Boolean mask of the one significant 6-connected component; tiny specks are dropped."""
    lab, n = ndimage.label(mask)
    if n <= 1:
        return mask
    sizes = np.bincount(lab.ravel())[1:]
    order = np.argsort(sizes)[::-1]
    significant = sizes >= min_fraction * sizes.sum()
    if significant.sum() > 1 and not keep_largest:
        listed = ", ".join(str(int(s)) for s in sizes[order][:6])
        raise LabelError(
            f"{name}: the structure is split into {int(significant.sum())} disconnected parts "
            f"of significant size (component sizes in voxels: {listed}). Fix the label map, "
            "choose the labels of one structure, or pass keep_largest=True to keep only the "
            "largest part."
        )
    return lab == order[0] + 1


def label_surface(
    label_map,
    *,
    labels: int | Sequence[int] = (1,),
    keep_largest: bool = False,
    min_component_fraction: float = 0.01,
    smoothing: float = 0.5,
    case_id: str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Boundary of a structure in a label map, as a triangle mesh in physical mm.

    Parameters
    ----------
    label_map : SimpleITK image, nibabel image or path
        3D integer label map.
    labels : int or sequence of int
        The structure is the union of these labels, e.g. ``(1, 2)`` for the MSD hippocampus.
    keep_largest : bool, default False
        If the structure has several disconnected parts of significant size, keep the
        largest instead of raising :class:`~medseg.errors.LabelError`.
    min_component_fraction : float, default 0.01
        Parts smaller than this fraction of the structure's voxels are specks and are dropped
        silently.
    smoothing : float, default 0.5
        Standard deviation, in voxels, of the Gaussian applied to the binary mask before
        marching cubes at level 0.5 (removes the staircase; 0 disables).
    case_id : str, optional
        Named in error messages.

    Returns
    -------
    vertices : (V, 3) float array, mm, (x, y, z)
        In the image's world frame (through :func:`medseg.io.voxel_to_physical`).
    faces : (F, 3) int array
        Triangles, oriented with outward normals.

    Raises
    ------
    LabelError
        No voxel carries ``labels``, or the structure is disconnected.
    """
    name = _case_name(case_id)
    image = _as_label_image(label_map, name)
    try:
        mask_img = select_labels(image, labels)
    except LabelError as exc:
        raise LabelError(f"{name}: {exc}") from None
    mask = sitk.GetArrayViewFromImage(mask_img).astype(bool)
    mask = _single_component(mask, name, keep_largest, min_component_fraction)
    vol = np.pad(mask.astype(np.float32), 2)
    if smoothing > 0:
        vol = ndimage.gaussian_filter(vol, sigma=float(smoothing))
    if vol.max() <= 0.5:
        raise LabelError(f"{name}: the structure is too thin to have a boundary at level 0.5")
    verts, faces, _, _ = marching_cubes(vol, level=0.5, allow_degenerate=False)
    verts = voxel_to_physical(image, verts - 2.0)
    faces = faces.astype(np.int64)
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    signed_volume = np.einsum("ij,ij->", v0, np.cross(v1, v2)) / 6.0
    if signed_volume < 0:
        faces = faces[:, ::-1].copy()
    return verts, faces


# ---------------------------------------------------------------------- mesh queries


def _polydata(vertices: np.ndarray, faces: np.ndarray) -> pv.PolyData:
    cells = np.hstack([np.full((len(faces), 1), 3), faces]).ravel()
    return pv.PolyData(np.asarray(vertices, float), cells)


def _closest_on_surface(mesh: pv.PolyData, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points on the triangles of ``mesh`` and their distances."""
    _, closest = mesh.find_closest_cell(np.asarray(points, float), return_closest_point=True)
    closest = np.asarray(closest, float).reshape(-1, 3)
    return closest, np.linalg.norm(closest - points, axis=1)
