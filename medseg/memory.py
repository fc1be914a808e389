"""Memory estimates and the guard that refuses a computation before it allocates.

The two allocations of medseg that grow with the problem are the triplet potential tables
(``C x L^3`` float32, copied and worked on by the MRF solver), estimated here, and the
per-voxel feature maps of the detectors (``voxels x F`` float32, plus the filters'
temporaries), estimated beside the features (:func:`medseg.detection.feature_map_bytes`).
The estimates give the peak in bytes from the sizes alone, before anything is allocated;
:func:`check_memory` compares an estimate with the configured limit and raises
:class:`~medseg.errors.ResourceLimitError` with the estimate, the limit and the way to lower
the estimate.

The limit, in order of precedence: an explicit keyword (``memory_limit_gb`` of
:class:`~medseg.ShapePriorSegmenter`, ``limit`` here); the environment variable
``MEDSEG_MEMORY_LIMIT_GB`` (what a ``medseg-segment`` user sets); otherwise
:data:`DEFAULT_FRACTION` of the machine's physical memory.

The estimates model the allocations of the code they guard (``TripletPrior.potential_tables``,
the MRF solvers, ``compute_features``) stage by stage; ``tests/test_resources.py`` compares
them with the peaks ``tracemalloc`` measures on the real calls.
"""

from __future__ import annotations

import math
import os

import numpy as np

from medseg.errors import ResourceLimitError

__all__ = [
    "ENV_VAR",
    "DEFAULT_FRACTION",
    "physical_memory_bytes",
    "memory_limit_bytes",
    "check_memory",
    "format_bytes",
    "potential_table_bytes",
    "potential_chunk_cliques",
    "solver_bytes",
    "triplet_mrf_bytes",
]

#: Environment variable holding the memory limit in gigabytes (GiB), e.g. ``8`` or ``0.5``.
ENV_VAR = "MEDSEG_MEMORY_LIMIT_GB"
#: Share of the physical memory one computation may use when no limit is configured.
DEFAULT_FRACTION = 0.5
#: The limit when the physical memory cannot be read (not Linux / macOS).
FALLBACK_LIMIT_BYTES = 4 * 2**30

_GIB = 2**30
#: Working memory of ``TripletPrior.potential_tables`` besides its result (its ``max_bytes``).
POTENTIAL_CHUNK_BYTES = 256 * 2**20
# Bytes per candidate triple of one chunk of potential_tables: the float32 invariant and
# its side sums, the mixture's running max / sum, centred and whitened coordinates, the
# component's log-density and the exp temporaries (41 to 61 bytes measured with tracemalloc
# on Gaussian and mixture densities on 2026-12-02, since the tables are computed in float32;
# 57 to 74 in float64). Also the rule that sizes the chunks.
BYTES_PER_TRIPLE = 52
# float64 temporaries of OrientationPrior.tables per candidate triple of one chunk of
# cliques: the dot product and the two squared norms summed over the coordinates, one
# coordinate's normal, direction and product, then the scale, the cosine and the cost
# (60-80 bytes measured with tracemalloc on 2026-12-04, L = 12..30, chunks of 4 and 16).
ORIENTATION_BYTES_PER_TRIPLE = 72
_KERNEL_CHUNK = 8 * 2**20  # medseg.mrf._kernels.CHUNK_BYTES
_SRMP_PREGATHER = 512 * 2**20  # medseg.mrf._srmp.PREGATHER_BYTES


# ----------------------------------------------------------------------------- the limit


def physical_memory_bytes() -> int | None:
    """Physical memory of the machine (bytes), or None where ``os.sysconf`` cannot tell."""
    try:
        pages = os.sysconf("SC_PHYS_PAGES")
        page = os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None
    if pages <= 0 or page <= 0:
        return None
    return int(pages) * int(page)


def _limit_and_source(limit: float | None) -> tuple[int, str]:
    if limit is not None:
        if not (isinstance(limit, int | float | np.number) and limit > 0 and math.isfinite(limit)):
            raise ResourceLimitError(
                f"the memory limit must be a positive number of bytes; got {limit!r}"
            )
        return int(limit), "set by the caller"
    text = os.environ.get(ENV_VAR, "").strip()
    if text:
        try:
            gb = float(text)
        except ValueError:
            gb = math.nan
        if not (gb > 0 and math.isfinite(gb)):
            raise ResourceLimitError(
                f"the environment variable {ENV_VAR}={text!r} is not a positive number of "
                f"gigabytes; set it to e.g. 8 (GiB) or unset it"
            )
        return int(gb * _GIB), f"from {ENV_VAR}={text}"
    total = physical_memory_bytes()
    if total is None:
        return FALLBACK_LIMIT_BYTES, "the default where the physical memory is unknown"
    return int(DEFAULT_FRACTION * total), (
        f"the default, {DEFAULT_FRACTION:.0%} of the machine's {format_bytes(total)}"
    )


def memory_limit_bytes(limit_gb: float | None = None) -> int:
    """The memory limit (bytes) one computation may use.

    Parameters
    ----------
    limit_gb : float, optional
        An explicit limit in GiB; default: ``MEDSEG_MEMORY_LIMIT_GB`` if set, else
        :data:`DEFAULT_FRACTION` of the physical memory.

    Raises
    ------
    ResourceLimitError
        ``limit_gb`` or the environment variable is not a positive number.
    """
    if limit_gb is not None:
        if not (isinstance(limit_gb, int | float | np.number) and limit_gb > 0):
            raise ResourceLimitError(
                f"`memory_limit_gb` must be a positive number of GiB; got {limit_gb!r}"
            )
        return int(float(limit_gb) * _GIB)
    return _limit_and_source(None)[0]


def format_bytes(nbytes: float) -> str:
    """Bytes as MiB (below 1 GiB) or GiB, e.g. ``'412.0 MiB'``, ``'12.50 GiB'``."""
    n = float(nbytes)
    if n >= _GIB:
        return f"{n / _GIB:.2f} GiB"
    mib = n / 2**20
    return f"{mib:.1f} MiB" if mib >= 0.1 else f"{mib:.3g} MiB"


def check_memory(
    nbytes: float,
    *,
    what: str,
    hint: str,
    limit: float | None = None,
    raise_with: str = f"memory_limit_gb=..., or the environment variable {ENV_VAR}",
) -> None:
    """Refuse a computation whose estimated memory exceeds the limit.

    Parameters
    ----------
    nbytes : float
        Estimated peak memory of the computation, bytes.
    what : str
        The computation, named for the user (e.g. ``"potential tables of 310 cliques x
        20^3 candidates"``).
    hint : str
        The concrete way to lower the estimate (fewer cliques, fewer candidates, a coarser
        stride, a smaller image).
    limit : float, optional
        Limit in bytes; default :func:`memory_limit_bytes` (``MEDSEG_MEMORY_LIMIT_GB`` or
        half the physical memory).
    raise_with : str
        How the caller raises the limit (an argument, the environment variable).

    Raises
    ------
    ResourceLimitError
        The message gives the estimate, the limit and where it comes from, the hint, and how
        to raise the limit.
    """
    limit_bytes, source = _limit_and_source(limit)
    if nbytes > limit_bytes:
        raise ResourceLimitError(
            f"{what} would need about {format_bytes(nbytes)} of memory, above the limit of "
            f"{format_bytes(limit_bytes)} ({source}). To lower it: {hint}. If the machine "
            f"has the memory, raise the limit ({raise_with})."
        )


# ----------------------------------------------------------------------------- potentials


def potential_table_bytes(
    n_cliques: int, n_candidates: int, *, chunk_bytes: int = POTENTIAL_CHUNK_BYTES
) -> int:
    """Peak memory (bytes) of ``TripletPrior.potential_tables``.

    Parameters
    ----------
    n_cliques : int
        C, triplet cliques.
    n_candidates : int
        L, candidates per landmark.
    chunk_bytes : int
        The call's ``max_bytes`` (working memory of one chunk of cliques).

    Returns
    -------
    int
        The ``(C, L, L, L)`` float32 result plus the float64 temporaries of one chunk of
        cliques (at least one clique, at most ``chunk_bytes`` worth).
    """
    c, lab = int(n_cliques), int(n_candidates)
    chunk = potential_chunk_cliques(c, lab, chunk_bytes=chunk_bytes)
    return 4 * c * lab**3 + chunk * BYTES_PER_TRIPLE * lab**3


def potential_chunk_cliques(
    n_cliques: int, n_candidates: int, *, chunk_bytes: int = POTENTIAL_CHUNK_BYTES
) -> int:
    """Cliques evaluated together by ``potential_tables`` within ``chunk_bytes`` (>= 1)."""
    per_clique = BYTES_PER_TRIPLE * int(n_candidates) ** 3
    return int(max(1, min(int(n_cliques), chunk_bytes // per_clique)))


def solver_bytes(
    n_landmarks: int, n_cliques: int, n_candidates: int, *, method: str = "mplp"
) -> int:
    """Peak working memory (bytes) of :func:`medseg.mrf.solve` on a triplet MRF.

    Counts what the solver allocates besides the caller's tables: the working copy of the
    tables with forbidden entries made finite (float32, ``C L^3``); for SRMP the tables
    pre-gathered per variable (``4 C L^3`` float32 when that fits in 512 MiB); the float64
    messages (``C x 3 x L``, several copies for the subgradient method's trees); and the
    chunked kernel temporaries (a few 8 MiB blocks, or one factor when that is larger).

    Parameters
    ----------
    n_landmarks : int
        N, variables.
    n_cliques : int
        C, triplet factors.
    n_candidates : int
        L, labels per variable.
    method : {"mplp", "srmp", "subgradient"}
    """
    n, c, lab = int(n_landmarks), int(n_cliques), int(n_candidates)
    tables = 4 * c * lab**3
    messages = 8 * (3 * c + n) * lab
    # kernel temporaries: a float32 block of factors in the message updates, two float64
    # blocks in the final certificate (each at most 8 MiB, or one factor when larger)
    block32 = min(tables, max(_KERNEL_CHUNK, 4 * lab**3))
    block64 = min(2 * tables, max(_KERNEL_CHUNK // 2, 8 * lab**3))
    kernels = max(block32, 2 * block64)
    if method == "srmp":
        pregather = 4 * tables if 4 * tables <= _SRMP_PREGATHER else 0
        return tables + pregather + 4 * messages + kernels
    if method == "subgradient":  # its tree min-marginals convert one float64 block at a time
        return tables + 10 * messages + max(block32, block64)
    return tables + 3 * messages + kernels


def orientation_table_bytes(n_cliques: int, n_candidates: int, *, chunk_size: int = 16) -> int:
    """Peak memory (bytes) of ``OrientationPrior.tables``: the ``(C, L, L, L)`` float32
    result plus the float64 temporaries of one chunk of ``chunk_size`` cliques."""
    c, lab = int(n_cliques), int(n_candidates)
    return 4 * c * lab**3 + min(int(chunk_size), c) * ORIENTATION_BYTES_PER_TRIPLE * lab**3


def triplet_mrf_bytes(
    n_landmarks: int,
    n_cliques: int,
    n_candidates: int,
    *,
    method: str = "mplp",
    chunk_bytes: int = POTENTIAL_CHUNK_BYTES,
    orientation: bool = False,
) -> int:
    """Peak memory (bytes) of building the potential tables and solving the MRF.

    The tables stay alive during the solve, so the peak is the larger of the build
    (:func:`potential_table_bytes`, then with ``orientation`` the handedness tables that
    are added to them, :func:`orientation_table_bytes`) and the tables plus the solver's
    working memory (:func:`solver_bytes`).
    """
    tables = 4 * int(n_cliques) * int(n_candidates) ** 3
    build = potential_table_bytes(n_cliques, n_candidates, chunk_bytes=chunk_bytes)
    if orientation:
        build = max(build, tables + orientation_table_bytes(n_cliques, n_candidates))
    solve = tables + solver_bytes(n_landmarks, n_cliques, n_candidates, method=method)
    return max(build, solve)
