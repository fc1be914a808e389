"""Memory of the per-voxel feature maps, estimated before they are allocated.

The counterpart of :mod:`medseg.memory` for the detectors: ``voxels x F`` float32 feature
maps plus the filters' temporaries, modelled stage by stage on :func:`compute_features`
(``tests/test_resources.py`` compares the estimates with ``tracemalloc`` peaks).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.fft import next_fast_len

from medseg.detection._features import FeatureSettings
from medseg.errors import ParameterError

__all__ = ["feature_map_bytes", "detection_bytes"]

# float64 temporaries of the closed-form 3x3 eigenvalues, per voxel of one z-slab chunk
_EIG_TEMPORARIES = 26
_EIG_CHUNK = 8  # slabs per chunk in compute_features


def _feature_layout(settings) -> tuple[set, tuple, tuple, int]:
    if settings is None:
        settings = FeatureSettings()
    return (
        set(settings.kinds),
        tuple(settings.scales_mm),
        tuple(settings.shell_radii_mm),
        int(settings.n_features),
    )


def _shell_bytes(shape: np.ndarray, spacing: np.ndarray, radius_mm: float) -> int:
    """Peak of one shell feature: padded image, three complex spectra, the float32 result."""
    width = float(spacing.max())
    half = np.ceil((radius_mm + width) / spacing).astype(int)
    padded = shape + 2 * half
    fshape = [next_fast_len(int(p + 2 * h), True) for p, h in zip(padded, half, strict=True)]
    spectrum = 8 * int(np.prod(fshape[:-1])) * (fshape[-1] // 2 + 1)  # complex64
    return 4 * int(np.prod(padded)) + 3 * spectrum + 4 * int(np.prod(fshape))


def feature_map_bytes(
    shape: Sequence[int],
    *,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    settings=None,
) -> int:
    """Peak memory (bytes) of :func:`medseg.detection.compute_features` on one image.

    Parameters
    ----------
    shape : (3,) sequence of int
        Image size as a (Z, Y, X) voxel array (``sitk.GetArrayFromImage(image).shape``).
    spacing : (3,) sequence of float, mm
        Voxel spacing in the same (z, y, x) order (the shell kernels' size depends on it).
    settings : FeatureSettings, optional
        Default ``FeatureSettings()``.

    Returns
    -------
    int
        The ``(Z, Y, X, F)`` float32 result plus the largest working set of the filters:
        the normalised image, per scale the smoothed image, its 3 gradients and 6 Hessian
        entries (float32) with the float64 eigenvalue temporaries of an 8-slab chunk, the
        local-variance temporaries, and per shell radius the padded image and its FFT
        spectra.

    Notes
    -----
    The input image's own buffer is not counted. The opt-in ``"profile"`` / ``"ring"`` kinds
    are estimated more coarsely (their sampling frames, about 20 / 35 image-sized float32
    arrays).
    """
    shape = np.asarray(shape, dtype=np.int64)
    spacing = np.asarray(spacing, dtype=float)
    if shape.shape != (3,) or (shape < 1).any():
        raise ParameterError(f"`shape` must be three positive voxel counts (Z, Y, X); got {shape}")
    if spacing.shape != (3,) or not (spacing > 0).all():
        raise ParameterError(f"`spacing` must be three positive values in mm; got {spacing}")
    kinds, scales, radii, n_features = _feature_layout(settings)
    v = int(np.prod(shape))
    f4 = 4 * v
    normalise = 4 * f4  # the voxel array, the centred copy, the scaled copy, its float32 cast
    base = 4 * v * n_features + f4 + (f4 if "std" in kinds else 0)
    per_scale = 0
    if scales and kinds & {"smoothed", "gradient", "hessian", "log", "std"}:
        steps = [0]
        if kinds & {"hessian", "log"}:
            # 3 gradients, 6 Hessian entries, one np.gradient temporary; then either the
            # eigenvalues' float64 temporaries or the Laplacian's two float32 sums
            after = [2 * f4 if "log" in kinds else 0]
            if "hessian" in kinds:
                slab = v * min(1.0, _EIG_CHUNK / int(shape[0]))
                after.append(int(8 * _EIG_TEMPORARIES * slab))
            steps.append(10 * f4 + max(after))
        elif "gradient" in kinds:
            steps.append(6 * f4)
        if "std" in kinds:
            steps.append(4 * f4)
        per_scale = f4 + max(steps)  # + the smoothed image
    shell = 0
    if "shell" in kinds and radii:
        shell = max(_shell_bytes(shape, spacing, r) for r in radii)
    oriented = 0
    if "ring" in kinds:
        oriented = 35 * f4
    elif "profile" in kinds:
        oriented = 20 * f4
    return int(max(normalise, base + max(per_scale, shell, oriented)))


def detection_bytes(
    shape: Sequence[int],
    *,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    settings=None,
    n_landmarks: int,
    stride: int = 2,
) -> int:
    """Peak memory (bytes) of ``LandmarkDetector.candidates`` on one image.

    The feature maps (:func:`feature_map_bytes`), or, when larger, the feature maps kept
    while the voxels of the stride grid are scored: their feature rows (float32), the
    probabilities of every landmark (float64 and float32) and their voxel and physical
    coordinates.

    Parameters
    ----------
    shape, spacing, settings
        As for :func:`feature_map_bytes`.
    n_landmarks : int
        N, landmarks (one probability column each).
    stride : int
        Every ``stride``-th voxel per axis is scored.
    """
    n_features = _feature_layout(settings)[3]
    shape_arr = np.asarray(shape, dtype=np.int64)
    features = feature_map_bytes(shape, spacing=spacing, settings=settings)
    grid = int(np.prod(-(-shape_arr // max(1, int(stride)))))
    scoring = 4 * int(np.prod(shape_arr)) * n_features + grid * (
        4 * n_features + 28 * int(n_landmarks) + 96
    )
    return int(max(features, scoring))
