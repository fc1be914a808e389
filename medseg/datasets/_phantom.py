"""The synthetic phantom cohort: the package's embedded data set and whole-pipeline benchmark.

:func:`make_phantom_cohort` checks its arguments, draws one seed per subject from
``random_state`` (so subject ``i`` depends only on the seed and ``i``) and builds each
subject with :func:`._phantom_image.make_phantom_case`; the landmark sites are the same
parametric sites for every cohort built with the same counts. The anatomy is in
:mod:`._phantom_shape`, the image synthesis in :mod:`._phantom_image`.
"""

from __future__ import annotations

import numpy as np
from sklearn.utils import check_random_state

from medseg.datasets._cohort import Case, Cohort
from medseg.datasets._phantom_image import _PhantomSpec, make_phantom_case
from medseg.datasets._phantom_shape import phantom_landmark_index
from medseg.errors import ParameterError


def make_phantom_cohort(
    n_subjects: int = 20,
    *,
    n_landmarks: int = 30,
    anisotropic: bool = False,
    oblique: bool = False,
    random_state=None,
    n_surface_points: int = 2000,
    size: int = 64,
    max_rotation_deg: float = 30.0,
    scale_range: tuple[float, float] = (0.8, 1.25),
    max_translation_mm: float = 4.0,
    shape_variation: float = 1.0,
    neighbour_contrast: tuple[float, float] = (0.04, 0.08),
    n_distractors: int = 3,
    bias_strength: float = 0.15,
    noise_std: float = 0.06,
) -> Cohort:
    """Synthetic cohort: a bent, tapered, bumpy bean pressed against look-alike neighbours.

    The package's embedded default data and the benchmark of the whole pipeline. The target
    (label 1) is a star-shaped surface given by a radial function over the sphere in a
    straight frame (tapered ellipsoid, ~30 mm long, with a bump and a notch), whose long axis
    is bent along a circular arc; five smooth modes (length, thickness, taper, bend, bump
    height) vary it across subjects. It has no mirror or rotational symmetry. Two neighbour
    blobs with intensity within ``neighbour_contrast`` of the target's overlap part of its
    surface, so its boundary is visible only there where they do not touch it. The
    background is a smooth texture with distractor blobs. Each subject is posed by a random
    similarity transform, then a smooth multiplicative bias field and Rician noise are
    applied.

    Parameters
    ----------
    n_subjects : int, default 20
        One case per subject.
    n_landmarks : int, default 30
        Landmark sites, spread evenly (farthest-point sampling) over the mean surface.
    anisotropic : bool, default False
        1 x 1 x 2 mm (x, y, z) voxels instead of 1 mm isotropic; same field of view.
    oblique : bool, default False
        Tilt the image axes by 20 degrees about a random axis (per subject).
    random_state : int, RandomState or None
        Subject ``i`` depends only on the seed and ``i``: a cohort of 5 is the first five
        subjects of a cohort of 20 built with the same seed.
    n_surface_points : int, default 2000
        Dense corresponding surface sites in ``meta["surface_points"]``.
    size : int, default 64
        Field of view in mm along each axis (voxels at 1 mm).
    max_rotation_deg : float, default 30
        Rotation angle drawn uniformly in ``[0, max_rotation_deg]`` about a uniformly random
        axis.
    scale_range : (float, float), default (0.8, 1.25)
        Isotropic scale, log-uniform.
    max_translation_mm : float, default 4
        Translation drawn uniformly in ``[-t, t]`` mm per axis.
    shape_variation : float, default 1
        Standard deviation multiplier of the shape modes (0 gives the mean shape).
    neighbour_contrast : (float, float), default (0.04, 0.08)
        Relative intensity difference of the neighbours to the target (either sign).
    n_distractors : int, default 3
        Background blobs at 70-85 % of the target intensity, away from the target.
    bias_strength : float, default 0.15
        Peak relative amplitude of the multiplicative bias field.
    noise_std : float, default 0.06
        Rician noise standard deviation relative to the target intensity (100).

    Returns
    -------
    cohort : Cohort
        In-memory cases ``phantom_000``, ... with ``image`` (float32) and ``label`` (uint8,
        1 = target) SimpleITK images, ``landmarks`` (n_landmarks, 3) mm (x, y, z) and
        ``meta``:

        * ``surface_points`` (n_surface_points, 3) mm: boundary points, the same parametric
          sites in every subject;
        * ``landmark_index`` (n_landmarks,): indices of the landmarks into surface_points;
        * ``pose``: ``{"rotation": (3, 3), "scale": float, "translation": (3,)}`` with
          ``surface_points = scale * canonical_points @ rotation.T + translation``;
        * ``canonical_points`` (n_surface_points, 3) mm, ``rotation_deg``, ``shape_modes``
          (5,), ``contact`` (n_surface_points,) bool: sites touched by a neighbour,
          ``neighbour_intensity_ratio``, ``spacing``.

    Examples
    --------
    >>> cohort = make_phantom_cohort(2, random_state=0)
    >>> len(cohort), cohort[0].landmarks.shape
    (2, (30, 3))
    """
    if int(n_subjects) < 1:
        raise ParameterError(f"`n_subjects` must be at least 1, got {n_subjects}")
    if not 3 <= int(n_landmarks) <= int(n_surface_points):
        raise ParameterError(
            f"`n_landmarks` must be between 3 and n_surface_points={n_surface_points}, "
            f"got {n_landmarks}"
        )
    if not 0 < scale_range[0] <= scale_range[1]:
        raise ParameterError(f"`scale_range` must be 0 < low <= high, got {scale_range}")
    rng = check_random_state(random_state)
    seeds = rng.randint(0, np.iinfo(np.int32).max, size=int(n_subjects))
    landmark_index = phantom_landmark_index(int(n_landmarks), int(n_surface_points))
    spec = _PhantomSpec(
        n_surface_points=int(n_surface_points),
        size=int(size),
        anisotropic=anisotropic,
        oblique=oblique,
        max_rotation_deg=float(max_rotation_deg),
        scale_range=(float(scale_range[0]), float(scale_range[1])),
        max_translation_mm=float(max_translation_mm),
        shape_variation=float(shape_variation),
        neighbour_contrast=neighbour_contrast,
        n_distractors=int(n_distractors),
        bias_strength=float(bias_strength),
        noise_std=float(noise_std),
    )
    cases = []
    for i, seed in enumerate(seeds):
        image, label, meta = make_phantom_case(int(seed), spec, landmark_index)
        case_id = f"phantom_{i:03d}"
        cases.append(
            Case(
                case_id=case_id,
                subject=case_id,
                image=image,
                label=label,
                landmarks=meta["surface_points"][landmark_index].copy(),
                meta=meta,
            )
        )
    return Cohort(cases=cases, labels={"background": 0, "target": 1}, name="phantom", root=None)
