"""The methods compared in one evaluation run, and how each is built per fold.

A :class:`MethodSpec` is one estimator fitted once per fold (``fit(cohort)``) and one or more
named *variants* segmented from that fitted estimator (``segment(image, **kwargs)``). The
shape-prior segmenter gives two variants from one fit: the method itself
(``use_prior=True``) and the detection-only baseline (``use_prior=False``), so both see the
same forests, folds and seed. A variant's result can also be scored through another of its
label maps, as a *derived* method at no extra cost: ``shape_only`` is the shape prior's
label map before its regional stage (``Segmentation.shape_label``). An *oracle* is computed
from the variant's fitted estimator and the test case's reference landmarks: ``ceiling``
and ``ceiling_boundary``, the template carried onto perfect landmarks
(:mod:`medseg.evaluation.ceiling`), a yardstick, not a method.

Any estimator with ``fit(cohort) -> self`` and ``segment(image, **kwargs)`` returning an
object with ``.label`` (a SimpleITK image on the input's grid) and ``.landmarks`` ((N, 3) mm,
or None for a method without landmarks: its landmark errors are NaN) can be evaluated;
``.mrf.gap`` is recorded when present.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from medseg.errors import MedsegError

__all__ = [
    "MethodSpec",
    "METHOD_NAMES",
    "DEFAULT_METHODS",
    "DEFAULT_PERTURBATION",
    "default_methods",
    "resolve_methods",
]

#: Names accepted by :func:`resolve_methods` (and ``medseg-evaluate --methods``).
METHOD_NAMES = (
    "shape_prior",
    "shape_only",
    "detection",
    "asm",
    "asm_boundary",
    "multi_atlas",
    "ceiling",
    "ceiling_boundary",
)
#: The methods of a default run. ``multi_atlas`` is left out: it registers its 9 atlases to
#: every test input (the unperturbed case and each perturbed copy), about 5 s per input on
#: hippocampus crops, where the others share one fitted model and one detection.
DEFAULT_METHODS = ("shape_prior", "shape_only", "detection", "asm")
#: Conditions of the default pose-perturbation study (besides the unperturbed case): one of
#: each kind, rotation only, scale only, and the random similarity of the issue's protocol
#: (as many perturbed copies as the earlier default of three angles, so about the same cost).
#: Kept here, beside the default methods, because this module is light: the parser of
#: ``medseg-evaluate`` names both defaults without importing the evaluation itself.
DEFAULT_PERTURBATION = ("rot90", "scale1.25", "random")


@dataclass(frozen=True)
class MethodSpec:
    """One estimator per fold, and the named variants segmented from it.

    Parameters
    ----------
    estimator : callable
        Called as ``estimator(**params, random_state=seed)`` once per fold; the result must
        have ``fit(cohort)`` and ``segment(image, **kwargs)``.
    params : dict
        Constructor keyword arguments (besides ``random_state``).
    variants : dict of str to dict
        Method name (a column value of the results) to the ``segment`` keyword arguments.
    derived : dict of str to (str, str)
        Method name to ``(variant, attribute)``: the variant's result scored with its
        ``attribute`` as the label map (e.g. ``("shape_prior", "shape_label")``).
    oracles : dict of str to (str, callable)
        Method name to ``(variant, function)``: ``function(estimator, image,
        reference_landmarks)`` with the variant's fitted estimator and the test input's
        reference landmarks returns a result (``.label``, ``.landmarks``), or None when it
        cannot (no row is written).
    """

    estimator: Callable[..., Any]
    params: dict = field(default_factory=dict)
    variants: dict = field(default_factory=dict)
    derived: dict = field(default_factory=dict)
    oracles: dict = field(default_factory=dict)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.variants) + tuple(self.derived) + tuple(self.oracles)

    def derived_from(self, variant: str) -> dict[str, str]:
        """The derived methods of ``variant``: name to the attribute holding their label."""
        return {name: attr for name, (source, attr) in self.derived.items() if source == variant}

    def oracles_from(self, variant: str) -> dict[str, Callable]:
        """The oracles of ``variant``: name to their function."""
        return {name: fn for name, (source, fn) in self.oracles.items() if source == variant}

    def build(self, seed: int):
        """A fresh, unfitted estimator for one fold."""
        return self.estimator(**self.params, random_state=seed)


def default_methods(
    names: Iterable[str] = DEFAULT_METHODS,
    *,
    labels: Sequence[int] = (1,),
    n_landmarks: int | None = None,
    segmenter_params: dict | None = None,
    asm_params: dict | None = None,
    multi_atlas_params: dict | None = None,
) -> tuple[MethodSpec, ...]:
    """The method and its baselines, restricted to ``names``.

    Parameters
    ----------
    names : iterable of {"shape_prior", "shape_only", "detection", "asm", "multi_atlas"}
        "shape_prior" is :class:`medseg.segmenter.ShapePriorSegmenter`; "shape_only" its
        label map before the regional stage (the template warped onto its landmarks, from
        the same segmentation, which it implies); "detection" the same
        fitted model with ``use_prior=False`` (each landmark at its best candidate, same
        TPS); "asm" the active shape model baseline of :mod:`medseg.evaluation.baselines.asm`,
        "asm_boundary" the same with the segmenter's regional stage (one fit gives both);
        "multi_atlas" the affine multi-atlas registration with majority voting of
        :mod:`medseg.evaluation.baselines.multi_atlas` (no landmarks); "ceiling" and
        "ceiling_boundary" the shape prior's template on each case's reference landmarks,
        without and with the regional stage (:mod:`medseg.evaluation.ceiling`; they imply
        "shape_prior" like "shape_only" does).
    labels : sequence of int
        Labels forming the structure (their union).
    n_landmarks : int or None
        Landmarks per shape when they are computed from the label maps.
    segmenter_params, asm_params, multi_atlas_params : dict, optional
        Extra constructor arguments.
    """
    names = tuple(names)
    unknown = [n for n in names if n not in METHOD_NAMES]
    if unknown or not names:
        raise MedsegError(
            f"unknown method(s) {unknown or names!r}: choose among {', '.join(METHOD_NAMES)}"
        )
    specs = []
    seg_variants, derived, oracles = {}, {}, {}
    implied = ("shape_prior", "shape_only", "ceiling", "ceiling_boundary")
    if any(name in names for name in implied):
        seg_variants["shape_prior"] = {"use_prior": True}
    if "shape_only" in names:
        derived["shape_only"] = ("shape_prior", "shape_label")
    if "ceiling" in names or "ceiling_boundary" in names:
        from medseg.evaluation.ceiling import reference_ceiling

        for name, boundary in (("ceiling", False), ("ceiling_boundary", True)):
            if name in names:
                fn = functools.partial(reference_ceiling, boundary=boundary)
                oracles[name] = ("shape_prior", fn)
    if "detection" in names:
        seg_variants["detection"] = {"use_prior": False}
    if seg_variants:
        from medseg.segmenter import ShapePriorSegmenter

        params = {"n_landmarks": n_landmarks, "labels": tuple(labels)}
        params.update(segmenter_params or {})
        specs.append(MethodSpec(ShapePriorSegmenter, params, seg_variants, derived, oracles))
    if "asm" in names or "asm_boundary" in names:
        from medseg.evaluation.baselines import ASMBaseline

        params = {"labels": tuple(labels)}
        params.update(asm_params or {})
        if "asm_boundary" in names:  # one fit: the refined map, and before it the plain ASM's
            params["boundary"] = True
            derived = {"asm": ("asm_boundary", "shape_label")} if "asm" in names else {}
            specs.append(MethodSpec(ASMBaseline, params, {"asm_boundary": {}}, derived))
        else:
            specs.append(MethodSpec(ASMBaseline, params, {"asm": {}}))
    if "multi_atlas" in names:
        from medseg.evaluation.baselines import MultiAtlasBaseline

        params = {"labels": tuple(labels)}
        params.update(multi_atlas_params or {})
        specs.append(MethodSpec(MultiAtlasBaseline, params, {"multi_atlas": {}}))
    return tuple(specs)


def resolve_methods(
    methods: Iterable[str | MethodSpec], *, labels: Sequence[int], n_landmarks: int | None
) -> tuple[MethodSpec, ...]:
    """Method names and/or :class:`MethodSpec` objects -> specs; variant names must be unique."""
    methods = list(methods)
    names = [m for m in methods if isinstance(m, str)]
    specs = [m for m in methods if isinstance(m, MethodSpec)]
    if len(names) + len(specs) != len(methods):
        raise MedsegError("`methods` must hold method names or MethodSpec objects")
    if names:
        specs = list(default_methods(names, labels=labels, n_landmarks=n_landmarks)) + specs
    if not specs:
        raise MedsegError("`methods` is empty: give at least one method to evaluate")
    seen: list[str] = [n for s in specs for n in s.names]
    if len(set(seen)) != len(seen):
        raise MedsegError(f"method names must be unique, got {seen}")
    return tuple(specs)
