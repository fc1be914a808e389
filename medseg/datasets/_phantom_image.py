"""One phantom subject on a voxel grid: exact label, and an image that is hard on purpose.

The label is rasterised exactly: a voxel centre is inside when, mapped back to the straight
canonical frame of :mod:`._phantom_shape`, its distance from the centre is below the radial
function in its direction. The image is built from soft occupancies (a partial-volume edge),
neighbour blobs whose intensity is within a few percent of the target's and which overlap
part of its surface, a textured background with distractor blobs, a smooth multiplicative
bias field and Rician noise. :class:`_PhantomSpec` carries the settings every subject of a
cohort shares; their defaults and meaning are those of
:func:`~medseg.datasets.make_phantom_cohort`, their one home.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
from scipy import ndimage, special
from scipy.spatial.transform import Rotation
from sklearn.utils import check_random_state

from medseg.datasets._phantom_shape import (
    _N_MODES,
    _Shape,
    _site_frame,
    _unit,
    phantom_surface_directions,
)
from medseg.io import physical_to_voxel, voxel_to_physical

# Neighbour blobs: parametric direction of the contact site, semi-axes (normal, t1, t2) in mm.
_NEIGHBOUR_SITES = np.array(
    [
        [0.10, 1.00, 0.20],  # inside the curve (concave side), middle
        [-0.80, -0.25, -0.55],  # under the tail
    ]
)
_NEIGHBOUR_AXES = np.array([[8.0, 11.0, 9.0], [7.0, 9.0, 8.0]])

_TARGET_INTENSITY = 100.0
_BACKGROUND_INTENSITY = 50.0


@dataclass(frozen=True)
class _PhantomSpec:
    """Settings shared by every subject of one phantom cohort (see ``make_phantom_cohort``)."""

    n_surface_points: int
    size: int
    anisotropic: bool
    oblique: bool
    max_rotation_deg: float
    scale_range: tuple[float, float]
    max_translation_mm: float
    shape_variation: float
    neighbour_contrast: tuple[float, float]
    n_distractors: int
    bias_strength: float
    noise_std: float


def _soft_occupancy(level: np.ndarray, spacing_zyx: np.ndarray, width: float) -> np.ndarray:
    """Partial-volume occupancy in [0, 1] from an implicit function on the voxel grid.

    The implicit function is turned into an approximate signed distance in mm by dividing
    by its gradient norm, then smoothed by an error-function edge of ``width`` mm.
    """
    grads = np.gradient(level, *spacing_zyx)
    norm = np.sqrt(sum(g**2 for g in grads))
    distance = level / np.maximum(norm, 1e-3)
    return 0.5 * special.erfc(distance / (np.sqrt(2.0) * width))


def _grid_image(size_xyz, spacing_xyz, direction: np.ndarray) -> sitk.Image:
    """An empty image whose field of view is centred on the world origin."""
    image = sitk.Image([int(s) for s in size_xyz], sitk.sitkFloat32)
    image.SetSpacing([float(s) for s in spacing_xyz])
    image.SetDirection([float(v) for v in direction.ravel()])
    centre_index = (np.asarray(size_xyz, dtype=float) - 1.0) / 2.0
    offset = direction @ (np.asarray(spacing_xyz, dtype=float) * centre_index)
    image.SetOrigin([float(v) for v in -offset])
    return image


def _box(reference: sitk.Image, lo: np.ndarray, hi: np.ndarray) -> tuple[slice, ...]:
    """Array slices (z, y, x) covering the world-space box [lo, hi] (mm), clipped to the grid."""
    bounds = np.stack([lo, hi])
    corners = np.array([bounds[bits, [0, 1, 2]] for bits in np.ndindex(2, 2, 2)])
    zyx = physical_to_voxel(reference, corners)
    size_zyx = np.asarray(reference.GetSize())[::-1]
    start = np.clip(np.floor(zyx.min(axis=0)).astype(int) - 1, 0, size_zyx)
    stop = np.clip(np.ceil(zyx.max(axis=0)).astype(int) + 2, 0, size_zyx)
    return tuple(slice(int(a), int(b)) for a, b in zip(start, stop, strict=True))


def make_phantom_case(
    random_state, spec: _PhantomSpec, landmark_index: np.ndarray
) -> tuple[sitk.Image, sitk.Image, dict]:
    """One phantom subject: image, label and metadata (see ``make_phantom_cohort``)."""
    rng = check_random_state(random_state)
    modes = spec.shape_variation * rng.standard_normal(_N_MODES)
    shape = _Shape.from_modes(modes)
    size = spec.size

    # Canonical frame: the bent shape, centred on the centroid of its surface sites.
    directions = phantom_surface_directions(spec.n_surface_points)
    bent = shape.bend(shape.straight_points(directions))
    centroid = bent.mean(axis=0)
    canonical = bent - centroid

    # Pose: rotation by an angle up to max_rotation_deg about a uniformly random axis.
    axis = _unit(rng.standard_normal(3))
    angle = np.deg2rad(spec.max_rotation_deg) * rng.uniform(0.0, 1.0)
    rotation = Rotation.from_rotvec(angle * axis).as_matrix()
    low, high = spec.scale_range
    scale = float(np.exp(rng.uniform(np.log(low), np.log(high))))
    translation = rng.uniform(-spec.max_translation_mm, spec.max_translation_mm, size=3)
    surface = scale * canonical @ rotation.T + translation

    # Grid geometry.
    spacing = np.array([1.0, 1.0, 2.0]) if spec.anisotropic else np.ones(3)
    size_xyz = np.round(size / spacing).astype(int)
    if spec.oblique:
        tilt = Rotation.from_rotvec(np.deg2rad(20.0) * _unit(rng.standard_normal(3)))
        direction = tilt.as_matrix()
    else:
        direction = np.eye(3)
    reference = _grid_image(size_xyz, spacing, direction)
    shape_zyx = tuple(int(s) for s in size_xyz[::-1])
    spacing_zyx = spacing[::-1]
    # World position of every voxel centre: the grid is affine, so the helper maps the first
    # voxel and the three unit index steps, and the grid is their broadcast sum.
    corner, *steps = voxel_to_physical(reference, np.vstack([np.zeros(3), np.eye(3)]))
    world = corner + sum(
        np.arange(n, dtype=float).reshape([-1 if a == axis else 1 for a in range(3)] + [1])
        * (step - corner)
        for axis, (n, step) in enumerate(zip(shape_zyx, steps, strict=True))
    )
    fields = np.random.default_rng(rng.randint(np.iinfo(np.int32).max))
    width = 0.5  # mm, partial-volume edge of every structure

    def to_local(points: np.ndarray) -> np.ndarray:
        """World -> bent frame of the shape (inverse pose)."""
        return ((points - translation) @ rotation) / scale + centroid

    # Target: exact label at voxel centres, soft occupancy for the image; evaluated only in
    # a box around the surface sites (the shape is star-shaped inside their hull).
    box = _box(reference, surface.min(axis=0) - 2.0, surface.max(axis=0) + 2.0)
    target_level = shape.level(to_local(world[box].reshape(-1, 3))) * scale
    target_level = target_level.reshape(world[box].shape[:3])
    label = np.zeros(shape_zyx, dtype=np.uint8)
    label[box] = target_level < 0
    target = _soft_occupancy(target_level, spacing_zyx, width)

    # Background: smooth texture with distractor blobs of intermediate intensity.
    texture = ndimage.gaussian_filter(fields.standard_normal(shape_zyx), sigma=3.0 / spacing_zyx)
    image = _BACKGROUND_INTENSITY * (1.0 + 0.2 * texture / texture.std())
    for _ in range(spec.n_distractors):
        radii = rng.uniform(3.5, 7.0, size=3)
        for _attempt in range(50):
            centre = rng.uniform(-0.4 * size, 0.4 * size, size=3)
            if np.min(np.linalg.norm(surface - centre, axis=1)) > radii.max() + 3.0:
                break
        else:
            continue
        frame = Rotation.from_rotvec(rng.uniform(-np.pi, np.pi, 3)).as_matrix()
        sub = _box(reference, centre - radii.max() - 2.0, centre + radii.max() + 2.0)
        level = (
            np.linalg.norm(((world[sub] - centre) @ frame) / radii, axis=-1) - 1.0
        ) * radii.min()
        occ = _soft_occupancy(level, spacing_zyx, width)
        value = _TARGET_INTENSITY * rng.uniform(0.7, 0.85)
        image[sub] = image[sub] * (1.0 - occ) + value * occ

    # Neighbours of nearly the target's intensity, pressed into part of its surface.
    contact = np.zeros(spec.n_surface_points, dtype=bool)
    probe = bent + 0.75 * shape.normals(bent)
    neighbour_ratios = []
    for site, axes in zip(_NEIGHBOUR_SITES, _NEIGHBOUR_AXES, strict=True):
        point, frame = _site_frame(shape, _unit(site) + 0.12 * rng.standard_normal(3))
        axes = axes * rng.uniform(0.9, 1.1, size=3)
        centre_bent = point + frame[0] * (axes[0] - rng.uniform(2.5, 3.5))
        centre_world = scale * (centre_bent - centroid) @ rotation.T + translation
        reach = scale * axes.max() + 2.0
        sub = _box(reference, centre_world - reach, centre_world + reach)
        level = np.linalg.norm(((to_local(world[sub]) - centre_bent) @ frame.T) / axes, axis=-1)
        occ = _soft_occupancy((level - 1.0) * axes.min() * scale, spacing_zyx, width)
        ratio = 1.0 + rng.choice([-1.0, 1.0]) * rng.uniform(*spec.neighbour_contrast)
        neighbour_ratios.append(float(ratio))
        image[sub] = image[sub] * (1.0 - occ) + _TARGET_INTENSITY * ratio * occ
        # Surface sites whose outside neighbourhood (0.75 mm out) lies in this blob.
        contact |= np.linalg.norm(((probe - centre_bent) @ frame.T) / axes, axis=1) < 1.0

    # The target on top, with a faint inner texture.
    inner = ndimage.gaussian_filter(fields.standard_normal(target.shape), sigma=2.0 / spacing_zyx)
    inner_value = _TARGET_INTENSITY * (1.0 + 0.02 * inner / inner.std())
    image[box] = image[box] * (1.0 - target) + inner_value * target

    # Point spread, smooth multiplicative bias field, Rician noise.
    image = ndimage.gaussian_filter(image, sigma=0.5)
    x, y, z = np.moveaxis(world / (0.5 * size), -1, 0)
    terms = [x, y, z, x * y, y * z, x * z, x**2 - 1 / 3, y**2 - 1 / 3, z**2 - 1 / 3]
    coefficients = rng.uniform(-1.0, 1.0, size=len(terms))
    log_bias = sum(c * t for c, t in zip(coefficients, terms, strict=True))
    log_bias *= np.log1p(spec.bias_strength) / max(np.abs(log_bias).max(), 1e-9)
    image *= np.exp(log_bias)
    sigma = spec.noise_std * _TARGET_INTENSITY
    real = image + sigma * fields.standard_normal(shape_zyx)
    imag = sigma * fields.standard_normal(shape_zyx)
    image = np.sqrt(real**2 + imag**2)

    out = sitk.GetImageFromArray(image.astype(np.float32))
    out.CopyInformation(reference)
    lab = sitk.GetImageFromArray(label)
    lab.CopyInformation(reference)
    meta = {
        "surface_points": surface,
        "landmark_index": np.asarray(landmark_index, dtype=int).copy(),
        "pose": {"rotation": rotation, "scale": scale, "translation": translation},
        "rotation_deg": float(np.rad2deg(angle)),
        "canonical_points": canonical,
        "shape_modes": modes,
        "contact": contact,
        "neighbour_intensity_ratio": neighbour_ratios,
        "spacing": tuple(float(s) for s in spacing),
    }
    return out, lab, meta
