"""Baselines evaluated beside the shape-prior segmenter, on the same folds."""

from evaluation.baselines.asm import ASMBaseline, ASMResult

__all__ = ["ASMBaseline", "ASMResult"]
