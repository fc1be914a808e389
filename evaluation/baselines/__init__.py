"""Baselines evaluated beside the shape-prior segmenter, on the same folds.

* :class:`ASMBaseline`: the active shape model, searched from the image centre;
* :class:`MultiAtlasBaseline`: affine multi-atlas registration (Mattes MI), majority vote.
"""

from medseg.evaluation.baselines.asm import ASMBaseline, ASMResult
from medseg.evaluation.baselines.multi_atlas import MultiAtlasBaseline, MultiAtlasResult

__all__ = ["ASMBaseline", "ASMResult", "MultiAtlasBaseline", "MultiAtlasResult"]
