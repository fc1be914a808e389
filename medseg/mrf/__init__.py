"""MRF inference: dual decomposition into factor trees, min-sum BP, MPLP; graph cuts.

The solver sees plain arrays, never images: ``N`` variables (landmarks) with ``L_i`` labels
(candidates) each, unary costs, and factors of order 2 and 3 with dense cost tables.

>>> from medseg.mrf import MRF, solve
>>> mrf = MRF.from_triplets(unaries, cliques, tables)        # doctest: +SKIP
>>> res = solve(mrf)                                         # doctest: +SKIP
>>> res.x, res.energy, res.lower_bound, res.gap              # doctest: +SKIP
"""

from medseg.mrf._cut import (
    binary_cut_bound,
    binary_energy,
    grid_edges,
    minimize_binary,
    potts_energy,
    potts_expansion,
)
from medseg.mrf._exact import estimate_ilp_bytes, exhaustive_search, solve_ilp
from medseg.mrf._icm import icm
from medseg.mrf._model import DEFAULT_MAX_BYTES, MRF, FactorGroup
from medseg.mrf._mplp import colour_factors
from medseg.mrf._result import STATUS_MESSAGES, SolveResult, relative_gap
from medseg.mrf._solve import METHODS, estimate_solver_bytes, solve
from medseg.mrf._trees import factor_tree_cover, is_factor_forest

__all__ = [
    "MRF",
    "FactorGroup",
    "SolveResult",
    "STATUS_MESSAGES",
    "DEFAULT_MAX_BYTES",
    "METHODS",
    "solve",
    "estimate_solver_bytes",
    "exhaustive_search",
    "solve_ilp",
    "estimate_ilp_bytes",
    "icm",
    "factor_tree_cover",
    "is_factor_forest",
    "colour_factors",
    "relative_gap",
    "minimize_binary",
    "binary_cut_bound",
    "binary_energy",
    "potts_expansion",
    "potts_energy",
    "grid_edges",
]
