"""Conformal flattening of a genus-0 surface to the extended complex plane, and Möbius
transforms fixed by three point pairs.

The flattening follows Angenent, Haker, Tannenbaum & Kikinis (1999): puncture the surface at
one triangle and solve one sparse linear system with the cotangent Laplacian; the rest of the
sphere-like surface is mapped conformally onto the plane, the puncture going to infinity. The
map is unique up to a Möbius transform, which is exactly the freedom the matcher removes by
normalising triplets to the canonical positions (e^{2 pi i/3}, e^{4 pi i/3}, 1).

Points of the extended plane are also handled in homogeneous form ``(u, v)`` (``z = u / v``)
and on the Riemann sphere (inverse stereographic projection), where infinity is an ordinary
point and the chordal distance is bounded.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse.linalg import splu

from medseg.errors import MeshError, ProblemDefinitionError
from medseg.geometry import cotangent_laplacian, face_areas
from medseg.matching._mesh_check import _boundary_half_edges

__all__ = [
    "CANONICAL_TRIPLET",
    "conformal_flatten",
    "close_holes",
    "mobius_to_canonical",
    "mobius_from_triplets",
    "apply_mobius",
    "compose_mobius",
    "invert_mobius",
    "to_riemann_sphere",
]

CANONICAL_TRIPLET = np.exp(2j * np.pi * np.array([1.0, 2.0, 3.0]) / 3.0)
"""The canonical positions ``(e^{2 pi i/3}, e^{4 pi i/3}, 1)`` of a normalised triplet."""


def close_holes(vertices: ArrayLike, faces: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Close every boundary loop with a fan of triangles to a new centroid vertex.

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (F, 3) int array, consistently oriented

    Returns
    -------
    vertices : (V + H, 3) float array
        The input vertices first (indices unchanged), then one centroid per hole.
    faces : (F + B, 3) int array
        The input faces, then the fans (B boundary edges in total), oriented consistently.
    """
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    boundary = _boundary_half_edges(f)
    if len(boundary) == 0:
        return v, f
    nxt = dict(zip(boundary[:, 0].tolist(), boundary[:, 1].tolist(), strict=True))
    new_v, new_f = [v], [f]
    seen: set[int] = set()
    for start in boundary[:, 0].tolist():
        if start in seen:
            continue
        loop = [start]
        seen.add(start)
        cur = nxt[start]
        while cur != start:
            if cur in seen or cur not in nxt:
                raise MeshError("mesh boundary is not a set of simple loops; repair the mesh.")
            loop.append(cur)
            seen.add(cur)
            cur = nxt[cur]
        loop = np.asarray(loop)
        c = len(v) + len(new_v) - 1
        new_v.append(v[loop].mean(axis=0, keepdims=True))
        # boundary half-edge a->b has its face on the left; the fan uses b->a
        new_f.append(np.column_stack([np.roll(loop, -1), loop, np.full(len(loop), c)]))
    return np.vstack(new_v), np.vstack(new_f)


def conformal_flatten(
    vertices: ArrayLike, faces: ArrayLike, *, puncture: int | None = None
) -> np.ndarray:
    """Conformal map of a genus-0 surface onto the extended complex plane.

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (F, 3) int array
        A connected, consistently and outward oriented genus-0 mesh (see
        :func:`medseg.matching.check_mesh`). Holes are closed internally with
        :func:`close_holes`.
    puncture : int, optional
        Index of the face sent to infinity. Default: the face whose centroid is nearest to the
        vertex centroid (a central region, so that no protrusion lies between the puncture
        and the others; this keeps the exponential compression of protrusions smallest).

    Returns
    -------
    z : (V,) complex array
        Flattened position of each vertex. Orientation preserving: triangles that are
        counter-clockwise seen from outside are counter-clockwise in the plane.

    References
    ----------
    .. [1] Angenent, S., Haker, S., Tannenbaum, A. & Kikinis, R. "Conformal geometry and
       brain flattening." MICCAI 1999. doi:10.1007/10704282_31
    """
    v0 = np.asarray(vertices, float)
    n_orig = len(v0)
    v, f = close_holes(v0, faces)
    if puncture is None:
        centroids = v[f].mean(axis=1)
        puncture = int(np.argmin(np.linalg.norm(centroids - v0.mean(axis=0), axis=1)))
    if not 0 <= puncture < len(f):
        raise ProblemDefinitionError(f"puncture must be a face index in [0, {len(f) - 1}].")
    lap, _ = cotangent_laplacian(v, f)
    p, q, r = f[puncture]
    pq = v[q] - v[p]
    theta = np.dot(v[r] - v[p], pq) / np.dot(pq, pq)
    e = v[r] - (v[p] + theta * pq)
    b = np.zeros(len(v), dtype=complex)
    b[p] += -1.0 / np.linalg.norm(pq)
    b[q] += 1.0 / np.linalg.norm(pq)
    b[p] += 1j * (1.0 - theta) / np.linalg.norm(e)
    b[q] += 1j * theta / np.linalg.norm(e)
    b[r] += -1j / np.linalg.norm(e)
    # the system is singular (constants); it is consistent, so pin one vertex far away
    keep = np.ones(len(v), dtype=bool)
    pin = int(np.argmax(np.linalg.norm(v - v[p], axis=1)))
    keep[pin] = False
    sub = lap[keep][:, keep].tocsc()
    try:
        lu = splu(sub)
    except RuntimeError as exc:
        raise MeshError(f"conformal flattening failed: Laplacian is singular ({exc}).") from exc
    z = np.zeros(len(v), dtype=complex)
    z[keep] = lu.solve(b[keep].real) + 1j * lu.solve(b[keep].imag)
    # orientation: most triangles (outward, counter-clockwise) must stay counter-clockwise
    zf = z[f]
    signed = np.imag(np.conj(zf[:, 1] - zf[:, 0]) * (zf[:, 2] - zf[:, 0]))
    w = face_areas(v, f)
    if np.sum(w * np.sign(signed)) < 0:
        z = np.conj(z)
    z = z - z[pin]
    return z[:n_orig]


def mobius_to_canonical(triplets: ArrayLike) -> np.ndarray:
    """Möbius transforms sending each triplet to the canonical triplet.

    Parameters
    ----------
    triplets : (..., 3) complex array
        Three distinct finite points per transform.

    Returns
    -------
    m : (..., 2, 2) complex array
        ``m @ [z, 1]`` is ``[a z + b, c z + d]``; normalised to determinant 1. Sends
        ``triplets[..., k]`` to ``CANONICAL_TRIPLET[k]`` (e^{2 pi i/3}, e^{4 pi i/3}, 1).
    """
    z = np.asarray(triplets, dtype=complex)
    if z.shape[-1] != 3:
        raise ProblemDefinitionError("triplets must have shape (..., 3).")
    return mobius_from_triplets(z, np.broadcast_to(CANONICAL_TRIPLET, z.shape))


def _to_zero_inf_one(z: np.ndarray) -> np.ndarray:
    """Matrix of ``z -> (z - z1)(z3 - z2) / ((z - z2)(z3 - z1))`` (z1->0, z2->inf, z3->1)."""
    z1, z2, z3 = z[..., 0], z[..., 1], z[..., 2]
    m = np.empty(z.shape[:-1] + (2, 2), dtype=complex)
    m[..., 0, 0] = z3 - z2
    m[..., 0, 1] = -z1 * (z3 - z2)
    m[..., 1, 0] = z3 - z1
    m[..., 1, 1] = -z2 * (z3 - z1)
    return m


def _normalise(m: np.ndarray) -> np.ndarray:
    det = m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] * m[..., 1, 0]
    return m / np.sqrt(det)[..., None, None]


def mobius_from_triplets(source: ArrayLike, target: ArrayLike) -> np.ndarray:
    """The unique Möbius transforms sending three points onto three points.

    Parameters
    ----------
    source, target : (..., 3) complex arrays
        Distinct finite points; ``source[..., k]`` is sent to ``target[..., k]``.

    Returns
    -------
    m : (..., 2, 2) complex array, determinant 1.

    Raises
    ------
    ProblemDefinitionError
        If two points of a triplet coincide (the transform is undefined).
    """
    s = np.asarray(source, dtype=complex)
    t = np.asarray(target, dtype=complex)
    for name, z in (("source", s), ("target", t)):
        gaps = np.abs(z - np.roll(z, 1, axis=-1)).min(axis=-1)
        scale = np.maximum(np.abs(z).max(axis=-1), 1.0)
        if np.any(gaps <= 1e-12 * scale):
            raise ProblemDefinitionError(f"{name} triplet has coinciding points.")
    return _normalise(invert_mobius(_to_zero_inf_one(t)) @ _to_zero_inf_one(s))


def invert_mobius(m: ArrayLike) -> np.ndarray:
    """Inverse of Möbius matrices (..., 2, 2) (the adjugate, determinant preserved)."""
    m = np.asarray(m, dtype=complex)
    out = np.empty_like(m)
    out[..., 0, 0] = m[..., 1, 1]
    out[..., 1, 1] = m[..., 0, 0]
    out[..., 0, 1] = -m[..., 0, 1]
    out[..., 1, 0] = -m[..., 1, 0]
    return out


def compose_mobius(outer: ArrayLike, inner: ArrayLike) -> np.ndarray:
    """Matrix of ``outer o inner`` (apply ``inner`` first), (..., 2, 2)."""
    return _normalise(np.asarray(outer, complex) @ np.asarray(inner, complex))


def apply_mobius(m: ArrayLike, z: ArrayLike) -> np.ndarray:
    """Apply Möbius transforms to points of the plane.

    Parameters
    ----------
    m : (..., 2, 2) complex array
    z : (..., N) complex array
        Broadcast against ``m``'s leading dimensions.

    Returns
    -------
    w : (..., N) complex array
        ``(a z + b) / (c z + d)``; ``inf`` (complex) where the denominator vanishes.
    """
    m = np.asarray(m, complex)
    z = np.asarray(z, complex)
    a, b = m[..., 0, 0, None], m[..., 0, 1, None]
    c, d = m[..., 1, 0, None], m[..., 1, 1, None]
    num, den = a * z + b, c * z + d
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den == 0, complex(np.inf, np.inf), num / den)


def to_riemann_sphere(z: ArrayLike, m: ArrayLike | None = None) -> np.ndarray:
    """Inverse stereographic projection of ``m(z)`` onto the unit sphere.

    Parameters
    ----------
    z : (..., N) complex array
    m : (..., 2, 2) complex array, optional
        Möbius transforms applied first, in homogeneous form (exact at infinity).

    Returns
    -------
    s : (..., N, 3) float array
        Unit vectors; 0 maps to the south pole (0, 0, -1), infinity to the north pole, the
        unit circle (hence the canonical triplet) to the equator.
    """
    z = np.asarray(z, complex)
    if m is None:
        u, w = z, np.ones_like(z)
    else:
        m = np.asarray(m, complex)
        u = m[..., 0, 0, None] * z + m[..., 0, 1, None]
        w = m[..., 1, 0, None] * z + m[..., 1, 1, None]
    uw = u * np.conj(w)
    nu, nw = np.abs(u) ** 2, np.abs(w) ** 2
    den = nu + nw
    return np.stack([2 * uw.real / den, 2 * uw.imag / den, (nu - nw) / den], axis=-1)
