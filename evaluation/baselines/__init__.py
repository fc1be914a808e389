"""Baselines evaluated beside the shape-prior segmenter, on the same folds."""

from medseg.evaluation.baselines.asm import ASMBaseline, ASMResult

__all__ = ["ASMBaseline", "ASMResult"]
