"""Baselines evaluated beside the shape-prior segmenter, on the same folds."""

from evaluation.baselines.asm import (
    ActiveShapeModel,
    ASMResult,
    PointDistributionModel,
    landmark_mesh,
    point_distribution_model,
    vertex_normals,
)

__all__ = [
    "ActiveShapeModel",
    "ASMResult",
    "PointDistributionModel",
    "point_distribution_model",
    "landmark_mesh",
    "vertex_normals",
]
