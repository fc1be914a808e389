"""The phantom's anatomy: a bent, tapered, bumpy bean, and its fixed surface sites.

The target is a star-shaped surface defined by a radial function over the unit sphere in a
straight canonical frame, whose long axis is then bent along a circular arc; five smooth
shape modes (length, thickness, taper, bend, bump height) vary it across subjects. Surface
sites are fixed directions on the sphere (a Fibonacci lattice), so the same site index is the
same anatomical point in every subject: correspondence is exact ground truth. Nothing here
knows images or voxels; :mod:`._phantom_image` rasterises this shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from medseg.geometry import farthest_point_sampling

__all__ = ["phantom_landmark_index", "phantom_surface_directions"]

# Fixed anatomy of the phantom, in the straight canonical frame (mm). The long axis is x,
# the bend goes towards +y (so +y is the concave side), z is "up".
_HALF_LENGTH = 15.0  # a: semi-axis along the long axis
_HALF_WIDTH = 7.0  # b: semi-axis along y at the middle
_HALF_HEIGHT = 5.5  # c: semi-axis along z at the middle
_TAPER = 0.35  # radii across the axis grow by (1 + taper * u_x): wide head at +x
_CURVATURE = 1.0 / 30.0  # 1/mm: bend of the long axis
_BUMP_DIRECTIONS = np.array(
    [
        [0.45, -0.75, 0.50],  # a bump on the convex side of the head, upper part
        [-0.30, 0.20, 0.93],  # a notch on top of the tail
    ]
)
_BUMP_HEIGHTS = np.array([0.30, -0.20])  # relative change of the radius at the peak
_BUMP_CONCENTRATION = 7.0  # von Mises concentration of the bumps over the sphere
_N_MODES = 5  # length, thickness, taper, bend, bump height


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def phantom_surface_directions(n_points: int) -> np.ndarray:
    """Fixed parametric surface sites: a Fibonacci lattice on the unit sphere.

    Parameters
    ----------
    n_points : int
        Number of sites.

    Returns
    -------
    directions : (n_points, 3) float array
        Unit vectors in the straight canonical frame; site ``m`` is the surface point
        ``r(u_m) u_m`` of every subject, hence in exact correspondence across subjects.
    """
    m = np.arange(n_points, dtype=float) + 0.5
    z = 1.0 - 2.0 * m / n_points
    phi = np.pi * (1.0 + 5.0**0.5) * m
    rho = np.sqrt(1.0 - z**2)
    return np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])


@dataclass(frozen=True)
class _Shape:
    """Shape parameters of one subject (straight canonical frame, mm)."""

    a: float
    b: float
    c: float
    taper: float
    curvature: float
    bump_heights: np.ndarray

    @classmethod
    def from_modes(cls, coefficients: np.ndarray) -> _Shape:
        z = np.clip(np.asarray(coefficients, dtype=float), -2.5, 2.5)
        thick = 1.0 + 0.08 * z[1]
        return cls(
            a=_HALF_LENGTH * (1.0 + 0.08 * z[0]),
            b=_HALF_WIDTH * thick,
            c=_HALF_HEIGHT * thick,
            taper=_TAPER + 0.08 * z[2],
            curvature=_CURVATURE * (1.0 + 0.25 * z[3]),
            bump_heights=_BUMP_HEIGHTS * (1.0 + 0.25 * z[4]),
        )

    def radius(self, u: np.ndarray) -> np.ndarray:
        """Radial function r(u) in mm for unit vectors ``u`` (N, 3)."""
        w = 1.0 + self.taper * u[:, 0]
        r0 = 1.0 / np.sqrt(
            (u[:, 0] / self.a) ** 2 + (u[:, 1] / (self.b * w)) ** 2 + (u[:, 2] / (self.c * w)) ** 2
        )
        cosines = u @ _unit(_BUMP_DIRECTIONS).T
        bumps = np.exp(_BUMP_CONCENTRATION * (cosines - 1.0)) @ self.bump_heights
        return r0 * (1.0 + bumps)

    def straight_points(self, u: np.ndarray) -> np.ndarray:
        return self.radius(u)[:, None] * u

    def bend(self, p: np.ndarray) -> np.ndarray:
        """Bend the straight x axis along a circle of radius 1/curvature towards +y."""
        R = 1.0 / self.curvature
        theta = p[:, 0] / R
        arm = R - p[:, 1]
        return np.column_stack([arm * np.sin(theta), R - arm * np.cos(theta), p[:, 2]])

    def unbend(self, q: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`bend` (valid away from the centre of curvature)."""
        R = 1.0 / self.curvature
        dy = R - q[:, 1]
        return np.column_stack([R * np.arctan2(q[:, 0], dy), R - np.hypot(q[:, 0], dy), q[:, 2]])

    def normals(self, q: np.ndarray, *, h: float = 1e-3) -> np.ndarray:
        """Outward unit normals at bent-frame points ``q`` (N, 3): the level-set gradient."""
        grad = np.stack([self.level(q + h * e) - self.level(q - h * e) for e in np.eye(3)], axis=1)
        return _unit(grad)

    def level(self, q: np.ndarray) -> np.ndarray:
        """Implicit function, negative inside: |p| - r(p/|p|) for p = unbend(q), in mm."""
        p = self.unbend(q)
        rho = np.linalg.norm(p, axis=1)
        u = p / np.maximum(rho, 1e-9)[:, None]
        return rho - self.radius(u)


def _mean_shape() -> _Shape:
    return _Shape.from_modes(np.zeros(_N_MODES))


def phantom_landmark_index(n_landmarks: int, n_surface_points: int) -> np.ndarray:
    """Indices of landmark sites spread evenly over the mean phantom surface.

    Farthest-point sampling over the surface sites of the mean shape, started at the tip of
    the head; the result depends only on the two counts, so landmarks of every phantom
    cohort built with the same counts are the same parametric sites.

    Parameters
    ----------
    n_landmarks : int
    n_surface_points : int

    Returns
    -------
    index : (n_landmarks,) int array
        Indices into the surface sites of :func:`phantom_surface_directions`.
    """
    shape = _mean_shape()
    points = shape.bend(shape.straight_points(phantom_surface_directions(n_surface_points)))
    tip = int(np.argmax(points[:, 0]))
    return np.asarray(farthest_point_sampling(points, n_landmarks, start=tip), dtype=int)


def _site_frame(shape: _Shape, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bent surface point at parametric ``direction`` and an orthonormal frame (n, t1, t2)."""
    point = shape.bend(shape.straight_points(_unit(direction)[None, :]))
    normal = shape.normals(point)[0]
    helper = np.array([0.0, 0.0, 1.0]) if abs(normal[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    t1 = _unit(np.cross(normal, helper))
    return point[0], np.stack([normal, t1, np.cross(normal, t1)])
