"""The higher-order MRF: variables with their own label counts, unary costs, factor tables."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from medseg import memory
from medseg.errors import ProblemDefinitionError

__all__ = ["MRF", "FactorGroup", "DEFAULT_MAX_BYTES"]

#: Default memory budget (bytes) for building or solving one problem; every function that
#: allocates in proportion to the factor tables takes ``max_bytes`` to change it.
DEFAULT_MAX_BYTES = 4 * 2**30

_MAX_ORDER = 3


@dataclass(frozen=True)
class FactorGroup:
    """All factors of one order, stored as one batch.

    Attributes
    ----------
    scopes : (C, k) int64 array
        Variable indices of each factor, in the order of the table axes.
    tables : (C, L, ..., L) float32 array
        ``tables[c]`` has ``k`` axes of length ``L = MRF.max_labels``; entries beyond a
        variable's own label count are ``+inf`` (forbidden).
    """

    scopes: np.ndarray
    tables: np.ndarray

    @property
    def order(self) -> int:
        return int(self.scopes.shape[1])

    def __len__(self) -> int:
        return int(self.scopes.shape[0])


def check_memory(estimate: float, max_bytes: float | None, what: str) -> None:
    """Raise :class:`ResourceLimitError` when ``estimate`` exceeds ``max_bytes``
    (default :data:`DEFAULT_MAX_BYTES`)."""
    limit = DEFAULT_MAX_BYTES if max_bytes is None else max_bytes
    memory.check_memory(
        estimate,
        what=what,
        hint="fewer labels or factors",
        limit=limit,
        raise_with=f"max_bytes=..., now {int(limit)}",
    )


def _check_costs(values: np.ndarray, name: str) -> None:
    if np.isnan(values).any():
        where = np.argwhere(np.isnan(values))[0]
        raise ProblemDefinitionError(
            f"{name} contains NaN (first at index {tuple(int(w) for w in where)}); costs must "
            "be finite numbers, or +inf to forbid a label combination"
        )
    if np.isneginf(values).any():
        where = np.argwhere(np.isneginf(values))[0]
        raise ProblemDefinitionError(
            f"{name} contains -inf (first at index {tuple(int(w) for w in where)}); costs "
            "must be finite, or +inf to forbid a label combination"
        )


def _as_unaries(unaries: ArrayLike | Sequence[ArrayLike]) -> tuple[np.ndarray, np.ndarray]:
    """Canonical (N, L_max) float64 unaries padded with +inf, and the label counts (N,)."""
    if isinstance(unaries, np.ndarray) or not isinstance(unaries, Sequence):
        arr = np.asarray(unaries, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[0] < 1 or arr.shape[1] < 1:
            raise ProblemDefinitionError(
                f"`unaries` must be an (N, L) array with N >= 1 variables and L >= 1 labels, "
                f"or a list of N one-dimensional cost vectors; got shape {arr.shape}"
            )
        _check_costs(arr, "`unaries`")
        return arr.copy(), np.full(arr.shape[0], arr.shape[1], dtype=np.int64)
    rows = []
    for i, row in enumerate(unaries):
        r = np.asarray(row, dtype=np.float64)
        if r.ndim != 1 or r.size < 1:
            raise ProblemDefinitionError(
                f"`unaries[{i}]` must be a non-empty one-dimensional cost vector; got shape "
                f"{r.shape}"
            )
        _check_costs(r, f"`unaries[{i}]`")
        rows.append(r)
    if not rows:
        raise ProblemDefinitionError("`unaries` is empty: the problem needs at least 1 variable")
    n_labels = np.array([r.size for r in rows], dtype=np.int64)
    out = np.full((len(rows), int(n_labels.max())), np.inf)
    for i, r in enumerate(rows):
        out[i, : r.size] = r
    return out, n_labels


def _check_scopes(scopes: np.ndarray, n_vars: int, name: str) -> None:
    if scopes.size and (scopes.min() < 0 or scopes.max() >= n_vars):
        bad = int(np.argwhere((scopes < 0) | (scopes >= n_vars))[0, 0])
        raise ProblemDefinitionError(
            f"{name}: factor {bad} has scope {scopes[bad].tolist()}, which names a variable "
            f"outside 0..{n_vars - 1} (the problem has {n_vars} variables)"
        )
    if scopes.shape[1] > 1:
        s = np.sort(scopes, axis=1)
        rep = (s[:, 1:] == s[:, :-1]).any(axis=1)
        if rep.any():
            bad = int(np.flatnonzero(rep)[0])
            raise ProblemDefinitionError(
                f"{name}: factor {bad} has scope {scopes[bad].tolist()} with a repeated "
                "variable; a factor must join distinct variables"
            )


class MRF:
    """A discrete higher-order Markov random field (energy to minimise).

    ``E(x) = sum_i U_i(x_i) + sum_f T_f(x_f)`` over labellings ``x`` with
    ``0 <= x_i < n_labels[i]``; factors ``f`` have order 1, 2 or 3 and dense cost tables.
    ``+inf`` marks a forbidden label or label combination; NaN and ``-inf`` are refused.

    Parameters
    ----------
    unaries : (N, L) array_like, or sequence of N one-dimensional array_like
        Unary costs; a sequence gives each variable its own number of labels ``L_i``.
    factors : iterable of (scope, table) pairs, optional
        ``scope`` is a sequence of 1 to 3 distinct variable indices, ``table`` an array of
        shape ``(L_{scope[0]}, ..., L_{scope[-1]})``. Order-1 factors are added to the
        unaries. Two factors on the same set of variables are refused (sum their tables).
    max_bytes : int, optional
        Memory budget for the stored (padded) tables; default :data:`DEFAULT_MAX_BYTES`.

    Attributes
    ----------
    n_variables : int
    n_labels : (N,) int64 array
    max_labels : int
    unaries : (N, max_labels) float64 array
        Padded with ``+inf`` beyond each variable's label count.
    groups : dict of int -> FactorGroup
        Factors of order 2 and 3, batched by order.

    See Also
    --------
    MRF.from_triplets : the batched constructor for the segmentation pipeline's problems.
    medseg.mrf.solve : minimise the energy by dual decomposition.

    Notes
    -----
    Mixed label counts are stored padded to ``max_labels`` with ``+inf``: memory is
    ``C * max_labels**k`` float32 per order ``k``.
    """

    def __init__(
        self,
        unaries: ArrayLike | Sequence[ArrayLike],
        factors: Iterable[tuple[Sequence[int], ArrayLike]] = (),
        *,
        max_bytes: int | None = None,
    ) -> None:
        self.unaries, self.n_labels = _as_unaries(unaries)
        n, lmax = self.unaries.shape
        by_order: dict[int, tuple[list, list]] = {}
        for f, item in enumerate(factors):
            try:
                scope, table = item
            except (TypeError, ValueError):
                raise ProblemDefinitionError(
                    f"`factors[{f}]` must be a (scope, table) pair; got {type(item).__name__}"
                ) from None
            scope = np.atleast_1d(np.asarray(scope))
            if scope.ndim != 1 or not 1 <= scope.size <= _MAX_ORDER:
                raise ProblemDefinitionError(
                    f"`factors[{f}]`: the scope must list 1 to {_MAX_ORDER} variables; got "
                    f"{scope.tolist()}"
                )
            if not np.issubdtype(scope.dtype, np.integer):
                raise ProblemDefinitionError(
                    f"`factors[{f}]`: the scope must hold integer variable indices; got "
                    f"{scope.tolist()}"
                )
            scope = scope.astype(np.int64)
            _check_scopes(scope[None], n, f"`factors[{f}]`")
            table = np.asarray(table, dtype=np.float64)
            expected = tuple(int(self.n_labels[v]) for v in scope)
            if table.shape != expected:
                raise ProblemDefinitionError(
                    f"`factors[{f}]` on variables {scope.tolist()} has a table of shape "
                    f"{table.shape}; it must be {expected} (the label counts of its variables)"
                )
            _check_costs(table, f"`factors[{f}]` table")
            scopes_k, tables_k = by_order.setdefault(scope.size, ([], []))
            scopes_k.append((f, scope))
            tables_k.append(table)
        if 1 in by_order:
            ids = np.array([s[0] for _, s in by_order[1][0]])
            uniq, counts = np.unique(ids, return_counts=True)
            if (counts > 1).any():
                v = int(uniq[counts > 1][0])
                raise ProblemDefinitionError(
                    f"`factors`: more than one order-1 factor on variable {v}; sum their "
                    "tables into one factor"
                )
            for (_, s), t in zip(*by_order.pop(1), strict=True):
                self.unaries[s[0], : t.size] += t
        estimate = sum(len(v[0]) * lmax**k * 4 for k, v in by_order.items())
        check_memory(estimate, max_bytes, "Storing the factor tables")
        self.groups: dict[int, FactorGroup] = {}
        for k in sorted(by_order):
            scopes_k, tables_k = by_order[k]
            scopes = np.stack([s for _, s in scopes_k])
            tables = np.full((len(tables_k),) + (lmax,) * k, np.inf, dtype=np.float32)
            for c, t in enumerate(tables_k):
                tables[(c,) + tuple(slice(0, d) for d in t.shape)] = t
            self.groups[k] = FactorGroup(scopes, tables)
        self._check_duplicates(list(self.groups.values()))

    @classmethod
    def from_triplets(
        cls,
        unaries: ArrayLike,
        cliques: ArrayLike,
        tables: ArrayLike,
        *,
        pairs: ArrayLike | None = None,
        pair_tables: ArrayLike | None = None,
    ) -> MRF:
        """Batched constructor: N variables with L labels each and triplet factors.

        Parameters
        ----------
        unaries : (N, L) array_like
            Unary costs, e.g. ``-log p(I | candidate)``.
        cliques : (C, 3) int array_like
            Variable indices of each triplet factor.
        tables : (C, L, L, L) array_like
            ``tables[c, a, b, d]`` is the cost of labels ``(a, b, d)`` on
            ``cliques[c]``; stored as float32 (no copy if it already is a C-contiguous
            float32 array).
        pairs : (P, 2) int array_like, optional
            Pairwise factors.
        pair_tables : (P, L, L) array_like, optional

        Returns
        -------
        MRF
        """
        self = cls.__new__(cls)
        self.unaries, self.n_labels = _as_unaries(np.asarray(unaries, dtype=np.float64))
        n, lab = self.unaries.shape
        self.groups = {}
        specs = [(3, cliques, tables, "cliques", "tables")]
        if pairs is not None or pair_tables is not None:
            if pairs is None or pair_tables is None:
                raise ProblemDefinitionError(
                    "`pairs` and `pair_tables` must be given together (or both left out)"
                )
            specs.insert(0, (2, pairs, pair_tables, "pairs", "pair_tables"))
        for k, sc, tb, sname, tname in specs:
            sc = np.asarray(sc)
            if sc.size == 0:
                sc = sc.reshape(0, k)
            if sc.ndim != 2 or sc.shape[1] != k or not np.issubdtype(sc.dtype, np.integer):
                raise ProblemDefinitionError(
                    f"`{sname}` must be an integer array of shape (C, {k}); got shape "
                    f"{sc.shape} and dtype {sc.dtype}"
                )
            sc = sc.astype(np.int64)
            tb = np.ascontiguousarray(tb, dtype=np.float32)
            expected = (sc.shape[0],) + (lab,) * k
            if tb.shape != expected:
                raise ProblemDefinitionError(
                    f"`{tname}` has shape {tb.shape}; with {sc.shape[0]} rows in `{sname}` "
                    f"and L={lab} labels (the columns of `unaries`) it must be {expected}"
                )
            _check_scopes(sc, n, f"`{sname}`")
            _check_costs(tb, f"`{tname}`")
            if len(sc):
                self.groups[k] = FactorGroup(sc, tb)
        self._check_duplicates(list(self.groups.values()))
        return self

    def _check_duplicates(self, groups: list[FactorGroup]) -> None:
        for g in groups:
            if len(g) < 2:
                continue
            s = np.sort(g.scopes, axis=1)
            _, first, counts = np.unique(s, axis=0, return_index=True, return_counts=True)
            if (counts > 1).any():
                dup = s[first[counts > 1][0]]
                idx = np.flatnonzero((s == dup).all(axis=1))
                raise ProblemDefinitionError(
                    f"factors {idx.tolist()} are all on variables {sorted(dup.tolist())}: "
                    "duplicated factors are not allowed; sum their tables into one factor"
                )

    # ------------------------------------------------------------------ properties
    @property
    def n_variables(self) -> int:
        return int(self.unaries.shape[0])

    @property
    def max_labels(self) -> int:
        return int(self.unaries.shape[1])

    @property
    def n_factors(self) -> int:
        return sum(len(g) for g in self.groups.values())

    def __repr__(self) -> str:
        orders = ", ".join(f"{len(g)} of order {k}" for k, g in self.groups.items())
        return (
            f"MRF({self.n_variables} variables, up to {self.max_labels} labels, "
            f"factors: {orders or 'none'})"
        )

    # ------------------------------------------------------------------ energy
    def check_labelling(self, x: ArrayLike, name: str = "x") -> np.ndarray:
        """Validate labellings: shape ``(..., N)`` integers within each label count."""
        arr = np.asarray(x)
        if arr.shape[-1:] != (self.n_variables,) or not np.issubdtype(arr.dtype, np.integer):
            raise ProblemDefinitionError(
                f"`{name}` must be an integer array with last axis of length "
                f"{self.n_variables} (one label per variable); got shape {arr.shape}, dtype "
                f"{arr.dtype}"
            )
        bad = (arr < 0) | (arr >= self.n_labels)
        if bad.any():
            where = np.argwhere(bad)[0]
            raise ProblemDefinitionError(
                f"`{name}` gives variable {int(where[-1])} the label {int(arr[tuple(where)])}, "
                f"outside 0..{int(self.n_labels[where[-1]]) - 1}"
            )
        return arr.astype(np.int64, copy=False)

    def energies(self, labellings: ArrayLike) -> np.ndarray:
        """Energies of a batch of labellings.

        Parameters
        ----------
        labellings : (M, N) int array_like

        Returns
        -------
        (M,) float64 array
            ``+inf`` for labellings that use a forbidden entry.
        """
        x = self.check_labelling(labellings, "labellings")
        return self._energies(np.atleast_2d(x))

    def _energies(self, x: np.ndarray) -> np.ndarray:
        """Energies of (M, N) valid labellings, without validation."""
        e = self.unaries[np.arange(self.n_variables), x].sum(axis=-1)
        for g in self.groups.values():
            idx = (np.arange(len(g)),) + tuple(x[:, g.scopes[:, q]] for q in range(g.order))
            e = e + g.tables[idx].astype(np.float64).sum(axis=-1)
        return e

    def energy(self, x: ArrayLike) -> float:
        """Energy of one labelling ``x`` of shape (N,); ``+inf`` if it uses a forbidden entry."""
        arr = self.check_labelling(x)
        if arr.ndim != 1:
            raise ProblemDefinitionError(
                f"`x` must be one labelling of shape ({self.n_variables},); got {arr.shape}; "
                "use energies() for a batch"
            )
        return float(self._energies(arr[None])[0])
