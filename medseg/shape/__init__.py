"""The pose-invariant higher-order shape prior (Wang et al., MICCAI 2010).

* :func:`relative_distances`, :func:`triangle_angles`: similarity-invariant descriptors of a
  triangle of landmarks; :func:`relative_distances_and_size` adds its size;
* :func:`select_cliques`, :func:`clique_table_size`: which triplets, and what their potential
  tables cost in memory;
* :class:`TripletPrior`: a density per clique, potentials ``H_c = -alpha log psi_c`` for one
  configuration or whole candidate tables, save / load without pickle;
* :class:`OrientationPrior`, :func:`triangle_orientation`: the handedness of each clique's
  triangle against the boundary directions, which the invariants above cannot see;
* :class:`ActiveShapeModel`, :func:`point_distribution_model`: the point distribution model
  with grey-level profiles and its search (Cootes et al. 1995), which refines the landmarks
  the MRF chose (and is the evaluation's baseline).
"""

from medseg.shape._active_shape import ActiveShapeModel, ShapeSearch
from medseg.shape._cliques import CliqueTableSize, clique_table_size, select_cliques
from medseg.shape._invariants import (
    relative_distances,
    relative_distances_and_size,
    triangle_angles,
)
from medseg.shape._orientation import OrientationPrior, triangle_orientation
from medseg.shape._point_distribution import (
    PointDistributionModel,
    landmark_mesh,
    point_distribution_model,
)
from medseg.shape._prior import MIN_TRAINING_SHAPES, TripletPrior

__all__ = [
    "relative_distances",
    "relative_distances_and_size",
    "triangle_angles",
    "select_cliques",
    "clique_table_size",
    "CliqueTableSize",
    "TripletPrior",
    "OrientationPrior",
    "triangle_orientation",
    "MIN_TRAINING_SHAPES",
    "ActiveShapeModel",
    "ShapeSearch",
    "PointDistributionModel",
    "point_distribution_model",
    "landmark_mesh",
]
