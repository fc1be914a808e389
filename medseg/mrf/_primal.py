"""Shared solver plumbing: best primal labelling, stopping rules, final min-marginals."""

from __future__ import annotations

import time

import numpy as np

from medseg.mrf._icm import Incidence, icm_improve
from medseg.mrf._model import MRF
from medseg.mrf._result import SolveResult, make_result

__all__ = [
    "PrimalTracker",
    "gap_closed",
    "Clock",
    "rounding_slack",
    "finish_min_marginals",
    "certified_result",
]


def gap_closed(energy: float, lower_bound: float, tol: float, atol: float) -> bool:
    """``energy - lower_bound <= max(tol * |energy|, atol)``."""
    return bool(np.isfinite(energy) and energy - lower_bound <= max(tol * abs(energy), atol))


def rounding_slack(big: float) -> float:
    """Float32 rounding allowance on energies (``big / 10`` bounds the sum of |costs|)."""
    return 1e-6 * big / 10.0


class PrimalTracker:
    """Keeps the best labelling seen; candidates that improve it get an ICM polish."""

    def __init__(self, mrf: MRF, *, local_search: bool, max_sweeps: int = 20) -> None:
        self.mrf = mrf
        self.inc = Incidence(mrf) if local_search else None
        self.max_sweeps = max_sweeps
        self.x = mrf.unaries.argmin(axis=1)
        self.energy = float(mrf._energies(self.x[None])[0])
        if self.inc is not None:
            self._polish()

    def _polish(self) -> None:
        x, _, _ = icm_improve(self.mrf, self.x, self.inc, max_sweeps=self.max_sweeps)
        e = float(self.mrf._energies(x[None])[0])
        if e < self.energy:
            self.x, self.energy = x, e

    def offer(self, x: np.ndarray) -> bool:
        """Consider labelling ``x`` (N,); returns whether the best energy improved."""
        e = float(self.mrf._energies(x[None])[0])
        if not e < self.energy:
            return False
        self.x, self.energy = x.copy(), e
        if self.inc is not None:
            self._polish()
        return True


class Clock:
    """Wall-clock since construction, and the time-limit test."""

    def __init__(self, time_limit: float | None) -> None:
        self.t0 = time.perf_counter()
        self.limit = time_limit

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def out_of_time(self) -> bool:
        return self.limit is not None and self.elapsed >= self.limit


def finish_min_marginals(mm: np.ndarray, mrf: MRF, big: float) -> np.ndarray:
    """Set padded labels and forbidden-level values to ``+inf``."""
    mm = np.asarray(mm, dtype=np.float64)
    valid = np.arange(mrf.max_labels)[None, :] < mrf.n_labels[:, None]
    return np.where(valid & (mm < big), mm, np.inf)


def certified_result(
    mrf: MRF,
    primal: PrimalTracker,
    lower: float,
    min_marginals: np.ndarray,
    *,
    big: float,
    status: int,
    n_iter: int,
    clock: Clock,
    tol: float,
    atol: float,
    history: tuple[list, list],
    method: str,
    **extra,
) -> SolveResult:
    """The result of a dual solver: its best labelling and the float64 certificate.

    A gap the float32 loop saw closed (``status`` 0) but the certificate ``lower`` does not
    confirm becomes status 2; ``history`` is the (energy, lower bound) per iteration.
    """
    if status == 0 and not gap_closed(primal.energy, lower, tol, atol + rounding_slack(big)):
        status = 2
    energies, bounds = history
    return make_result(
        x=primal.x,
        energy=primal.energy,
        lower_bound=lower,
        n_iter=n_iter,
        status=status,
        time=clock.elapsed,
        min_marginals=finish_min_marginals(min_marginals, mrf, big),
        history={"energy": np.asarray(energies), "lower_bound": np.asarray(bounds)},
        method=method,
        **extra,
    )
