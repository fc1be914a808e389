"""Landmarks in correspondence from training label maps.

Users have label maps, not landmarks. :func:`landmarks_from_labels` turns the label maps of
one structure (or of a union of labels) into ``N`` boundary landmarks per case that
correspond across cases:

1. the boundary of each label map by marching cubes (scikit-image), in physical mm through
   :func:`medseg.io.voxel_to_physical` (anisotropic and oblique images are handled);
2. a reference case (the one closest to the others, or a given one) and ``N`` landmarks
   spread over its surface by farthest-point sampling;
3. for every other case, the reference surface is aligned by its principal axes (the 4
   proper sign choices, or 8 with reflections, each refined by a similarity ICP; the best
   kept), then deformed onto the case by coherent point drift (non-rigid), and the deformed
   reference landmarks are projected onto the case's surface.

The fit residual of each case is the mean distance of the deformed reference surface to the
case's surface; cases whose residual exceeds a threshold are flagged as failed.

The package holds one idea per module: ``_surface`` (label map -> mesh in mm, and closest
points on a mesh), ``_transfer`` (the registration chain carrying landmarks onto one surface,
its last step alone from a surface onto a nearby one, and the settings they share with the
cohort entry), ``_cohort`` (the cohort-level entries and :class:`CorrespondenceResult`) and
``_plot`` (the figure). The point-set registration itself is :mod:`medseg.geometry`.

References
----------
.. [1] A. Myronenko and X. Song, "Point set registration: coherent point drift", IEEE TPAMI
   32(12), 2010. :doi:`10.1109/TPAMI.2010.46`
.. [2] W. E. Lorensen and H. E. Cline, "Marching cubes", SIGGRAPH 1987; T. Lewiner et al.,
   "Efficient implementation of marching cubes' cases with topological guarantees",
   J. Graphics Tools 8(2), 2003. :doi:`10.1080/10867651.2003.10487582`
"""

# VERTICES_PER_LANDMARK: importable here as before, though not in __all__
from medseg.correspondence._cohort import VERTICES_PER_LANDMARK as VERTICES_PER_LANDMARK
from medseg.correspondence._cohort import (
    CorrespondenceResult,
    cohort_landmarks,
    landmarks_from_labels,
)
from medseg.correspondence._plot import plot_correspondences
from medseg.correspondence._surface import label_surface
from medseg.correspondence._transfer import follow_boundary, transfer_landmarks

__all__ = [
    "CorrespondenceResult",
    "label_surface",
    "landmarks_from_labels",
    "cohort_landmarks",
    "transfer_landmarks",
    "follow_boundary",
    "plot_correspondences",
]
