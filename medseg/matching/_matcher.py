"""The matcher: :func:`match_surfaces` and its result :class:`SurfaceMatch`.

Dense surface matching in two stages (Zeng et al., CVPR 2010, Sec. 4), each step in its own
module:

1. Sparse stage (:mod:`medseg.matching._sparse`): farthest-point samples of A are matched to
   farthest-point samples of B with the third-order energy (descriptor singleton costs;
   Möbius, orientation and geodesic-distortion triplet costs).
2. Dense matching: the Möbius maps of the best matched triplets send every vertex of A to
   a vertex of B; these votes are clustered to their modes, which become the dense
   candidates (:mod:`medseg.matching._voting`), and each vertex takes its cheapest one
   (vote density and descriptor). With ``dense_stage=True`` (the paper's dense stage), the
   dense energy (those singleton costs, one third-order clique per face of A) is minimised
   by dual decomposition instead (:mod:`medseg.matching._dense`).

3. Refinement: the dense map is polished spectrally (:mod:`medseg.matching._spectral`).

This module runs the steps once per sparse solve and chooses among the solves' maps, for
the reasons below; what the sparse stage changed from the paper is in its module.

Mirror flips (session 3, FAUST). The whole-body left-right flips were not the orientation
term's fault: their sparse labellings were orientation-preserving (their trusted triplets
agreed in orientation with A's as often as the truth's did) and had a lower energy than
the truth's, because they map the body rotated half a turn (left to right and front to
back), which the descriptors, the Möbius and the geodesic terms hardly tell from the truth.
The refinement, started at 8 eigenpairs, then turned these maps into true mirror images,
and turned correct but noisy maps into front-back mirrors (errors near 0.09). Hence:

* :func:`spectral_refine` starts at 16 eigenpairs (keeps orientation; figures there);
* ``n_solves=2``: the sparse stage is solved a second time with the first solution's
  matches excluded; on eight FAUST pairs the two solves were always the truth's basin and
  the half-turn's, and the map with the lower descriptor residual was the right one in all
  eight (residual 0.46-2.94 against 0.78-3.23, one pair within 0.5 %);
* maps that mirror more than half of A (:func:`mirrored_fraction`) are not chosen.

The choice among solves (session 4, 15 FAUST and 15 TOSCA pairs, each solve's refined map
scored; 29 pairs where one solve was better by more than 0.03). On FAUST the wrong solve is
still the half-turn (direct error 0.50-0.56, 0.09-0.10 against the mirrored truth): it
preserves orientation, so the mirror test does not see it. The descriptor residual picked
the better solve in 25 of the 29 pairs; on FAUST tr_reg_069 -> tr_reg_077 the half-turn's
residual (5.04) is below even the ground truth's (5.18), so no descriptor criterion can.
Other criteria on the refined maps: signed mean curvature smoothed at three scales 23,
the mirrored fraction 27 (with margins of a few percent on FAUST), the log area ratio 25,
the share of B's vertices hit 25, the sparse energy 24; the spectral residual of the
refined map (:func:`spectral_residual`, ZoomOut's own energy at 80 eigenpairs: how far
B's pulled-back eigenfunctions are from spanning A's) 27, failing only on the pair above
and on TOSCA dog10 -> dog3 where both solves are poor (0.13 / 0.09). On the unrefined
maps every criterion did worse (spectral residual 20, descriptor residual 22). So each
solve is refined and the maps that are not mirrored are ranked by their spectral residual.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree
from sklearn.utils import check_random_state
from tqdm.auto import tqdm

from medseg.errors import ProblemDefinitionError
from medseg.geometry import face_areas, vertex_areas
from medseg.matching._dense import _best_candidates, _dense_stage
from medseg.matching._descriptors import mirrored_fraction
from medseg.matching._mesh_check import check_mesh
from medseg.matching._solver import SolveResult
from medseg.matching._sparse import _sparse_stage
from medseg.matching._spectral import spectral_refine, spectral_residual
from medseg.matching._surface import prepare_surface
from medseg.matching._voting import _dense_candidates

__all__ = ["SurfaceMatch", "match_surfaces"]


@dataclass
class SurfaceMatch:
    """Result of :func:`match_surfaces`.

    Attributes
    ----------
    forward : (V_A,) int array
        0-based index of the vertex of B matched to each vertex of A; -1 where A has no
        partner (only with ``partial=True``).
    matched : (V_A,) bool array
        The vertices of A that have a partner on B: all of them unless ``partial=True``,
        then those the map back from B comes near.
    forward_unrefined : (V_A,) int array
        The dense map before the spectral refinement (with ``dense_stage=True`` the paper's
        pipeline alone).
    forward_votes : (V_A,) int array
        Each vertex's best dense candidate (the sparse stage and the Möbius votes, without
        the dense stage), for ablations; ``forward_unrefined`` unless the dense stage ran.
    inverse : (V_B,) int array
        For each vertex of B, the vertex of A whose image is nearest to it on B; with
        ``partial=True`` the refined map back from B to A, -1 where no image of A comes
        within three mean edge lengths.
    sparse_pairs : (P, 2) int array
        Vertex pairs (A, B) matched by the sparse stage.
    sparse : SolveResult
        Solver outcome of the sparse stage (energy, lower bound, gap, ...).
    dense : SolveResult or None
        Solver outcome of the dense stage; None when it did not run (``dense_stage``).
    matched_fraction : float
        Fraction of vertices of A the dense solver matched (did not label "unmatched"); the
        rest took their best dense candidate. NaN without the dense stage.
    mirrored_fraction : float
        Share of A whose image on B is mirrored (:func:`mirrored_fraction`): near 0 for
        an orientation-preserving map, near 1 for a left-right flip.
    solves : list of dict
        Per sparse solve (``n_solves``): ``forward`` (its (V_A,) map), ``unrefined`` (its
        dense stage's map), ``mirrored`` (its map's mirrored fraction), ``spectral`` (its
        map's :func:`spectral_residual`, the selection criterion), ``residual``
        (area-weighted mean descriptor cost of its map) and ``energy`` (sparse energy).
    timings : dict
        Seconds per step, summed over the solves.
    """

    forward: np.ndarray
    matched: np.ndarray
    forward_unrefined: np.ndarray
    forward_votes: np.ndarray
    inverse: np.ndarray
    sparse_pairs: np.ndarray
    sparse: SolveResult
    dense: SolveResult
    matched_fraction: float
    mirrored_fraction: float
    solves: list
    timings: dict


def _choose_solve(mirrored, residual, *, max_mirrored: float) -> int:
    """Index of the solve to keep: among the maps whose mirrored fraction is at most
    ``max_mirrored`` (if none, the least mirrored), the lowest residual (the matcher passes
    the spectral residual)."""
    mirrored = np.asarray(mirrored, float)
    mirrored = np.where(np.isfinite(mirrored), mirrored, 1.0)  # no triangle image: rejected
    ok = mirrored <= max_mirrored
    if not ok.any():
        ok = mirrored == mirrored.min()
    return int(np.argmin(np.where(ok, np.asarray(residual, float), np.inf)))


def _mean_edge(surface) -> float:
    f = surface.faces
    return float(
        np.linalg.norm(surface.vertices[f] - surface.vertices[np.roll(f, 1, 1)], axis=-1).mean()
    )


def _partial_cover(a, b, forward, inverse, *, refine):
    """What has a partner when one surface may be part of the other.

    The map back from B to A starts from ``inverse`` (each vertex of B to the vertex of A
    whose image is nearest) and is refined as the forward map is. A vertex of A has a
    partner if the map back comes within three mean edge lengths of it; a vertex of B, if
    the forward map does. Returns the map back, A's mask and B's mask.

    Why both directions: where B lacks a limb that A has twice (a leg of a body), the
    forward map sends both of A's legs onto B's one, and every vertex of B is covered;
    the map back, a function on B, chooses one of A's legs. Descriptors, geodesic
    consistency with the sparse matches and the dense stage's costs did not tell the lost
    leg's vertices (their best candidates cost less than those of vertices with a partner
    on FAUST tr_reg_026 -> tr_reg_050 with a leg of B cut), the map back does.
    """
    back = inverse
    if refine:
        back = spectral_refine(
            inverse,
            b.evecs,
            vertex_areas(b.vertices, b.faces),
            a.evecs,
            samples_a=b.spectral_samples,
            samples_b=a.spectral_samples,
        )
    near_a, _ = cKDTree(a.vertices[back]).query(a.vertices)
    near_b, _ = cKDTree(b.vertices[forward]).query(b.vertices)
    return back, near_a <= 3 * _mean_edge(a), near_b <= 3 * _mean_edge(b)


def _attempt(
    a,
    b,
    *,
    exclude,
    n_sparse,
    n_sparse_targets,
    n_candidates,
    n_triplets,
    n_align,
    n_vote,
    n_modes,
    mode_radius,
    refine,
    dense,
    mass_a,
    opts,
    rng,
):
    """Sparse stage, dense candidates, dense stage (if ``dense``) and refinement; the map's
    mirrored fraction."""
    timings = {}
    t0 = time.perf_counter()
    pairs, targets, sparse_res = _sparse_stage(
        a,
        b,
        n_sparse=n_sparse,
        n_targets=n_sparse_targets,
        n_candidates=n_candidates,
        n_triplets=n_triplets,
        n_align=n_align,
        opts=opts,
        rng=rng,
        exclude=exclude,
    )
    timings["sparse"] = time.perf_counter() - t0
    if len(pairs) < 3:
        raise ProblemDefinitionError(
            f"the sparse stage matched only {len(pairs)} points; the surfaces are too "
            "different to be matched (or increase n_candidates)."
        )
    t0 = time.perf_counter()
    modes, dens = _dense_candidates(
        a,
        b,
        pairs,
        n_vote=n_vote,
        n_align=n_align,
        n_modes=n_modes,
        radius=mode_radius,
        opts=opts,
        rng=rng,
    )
    timings["candidates"] = time.perf_counter() - t0
    if dense:
        t0 = time.perf_counter()
        forward, dense_res, matched, voted = _dense_stage(a, b, modes, dens, opts=opts)
        timings["dense"] = time.perf_counter() - t0
    else:
        voted = forward = _best_candidates(a, b, modes, dens, opts=opts)
        dense_res, matched = None, np.ones(len(forward), dtype=bool)
    unrefined = forward
    # on a partial match only the matched vertices speak for the map
    fit = matched if opts["partial"] else np.ones(len(forward), dtype=bool)
    t0 = time.perf_counter()
    if refine:
        forward = spectral_refine(
            forward,
            a.evecs,
            mass_a,
            b.evecs,
            samples_a=a.spectral_samples,
            samples_b=b.spectral_samples,
            fit=fit,
        )
    cover = None
    if opts["partial"]:  # what has a partner, by the map back (see _partial_cover)
        _, inverse = cKDTree(b.vertices[forward]).query(b.vertices)
        cover = _partial_cover(a, b, forward, inverse, refine=refine)
        fit = cover[1]
    spectral = spectral_residual(forward[fit], a.evecs[fit], mass_a[fit], b.evecs)
    timings["refine"] = time.perf_counter() - t0
    return {
        "cover": cover,
        "pairs": pairs,
        "targets": targets,
        "sparse": sparse_res,
        "dense": dense_res,
        "matched": matched,
        "forward": forward,
        "unrefined": unrefined,
        "voted": voted,
        "mirrored": mirrored_fraction(a.vertices, a.faces, b.vertices, b.normals, forward),
        "spectral": spectral,
        # the dense stage's descriptor cost, area-weighted over A (what has a partner)
        "residual": float(
            mass_a[fit]
            @ ((a.descriptor[fit] - b.descriptor[forward[fit]]) ** 2).sum(axis=1)
            / mass_a[fit].sum()
        ),
        "timings": timings,
    }


def match_surfaces(
    vertices_a: ArrayLike,
    faces_a: ArrayLike,
    vertices_b: ArrayLike,
    faces_b: ArrayLike,
    *,
    n_sparse: int = 30,
    n_sparse_targets: int = 150,
    n_candidates: int = 6,
    n_triplets: int = 120,
    n_align: int = 150,
    n_vote: int = 100,
    n_modes: int = 3,
    mode_radius: float = 0.05,
    lambda_descriptor: float = 1.0,
    lambda_mobius: float = 1.0,
    lambda_gauss: float = 1.0,
    lambda_geodesic: float = 0.5,
    orientation: str = "intrinsic",
    n_neighbours: int = 5,
    delta: float = 0.2,
    max_iter: int = 300,
    dense_max_iter: int = 100,
    dense_one_to_one: bool = False,
    refine: bool = True,
    dense_stage: bool = False,
    n_solves: int = 2,
    max_mirrored: float = 0.5,
    exclude_radius: float = 0.1,
    partial: bool = False,
    random_state=None,
    progress: bool = False,
) -> SurfaceMatch:
    """Dense vertex-to-vertex correspondence from surface A to surface B.

    Parameters
    ----------
    vertices_a : (V_A, 3) float array
        Surface A; any unit (each surface is scaled to unit area internally, so A and B may
        even be in different units).
    faces_a : (F_A, 3) int array
        Genus-0 triangle mesh (closed, or with holes); see :func:`check_mesh`.
    vertices_b, faces_b : arrays
        Surface B.
    n_sparse : int
        Farthest-point samples of A matched in the sparse stage.
    n_sparse_targets : int
        Farthest-point samples of B they may be matched to.
    n_candidates : int
        Candidates per sparse point (nearest in descriptor space). 5 would take 0.87 times
        the time (125 label combinations per clique instead of 216) and did as well on 10
        FAUST + 10 TOSCA pairs, but on the small bent surface of the tests the true match
        was then often not a candidate (mean error 0.12 instead of 0.018).
    n_triplets : int
        Third-order cliques sampled among the sparse points.
    n_align : int
        Samples per surface used to measure a Möbius alignment (mutually closest points).
    n_vote : int
        Best matched triplets whose Möbius maps vote for the dense candidates.
    n_modes : int
        Dense candidates per vertex (modes of its votes).
    mode_radius : float
        Kernel radius of the vote clustering, in units of ``sqrt(area)``.
    lambda_descriptor, lambda_mobius, lambda_gauss : float
        Weights of the singleton, Möbius (dense stage: edge-length distortion) and
        Gaussian-map (orientation) terms.
    lambda_geodesic : float
        Weight of the sparse stage's geodesic-distortion term (0 turns it off).
    orientation : {"intrinsic", "normals"}
        Orientation test of the sparse stage: orientation of geodesic triangles in log maps
        (default), or the paper's sign of the normals' determinant.
    n_neighbours : int
        Geodesic neighbours of each sparse point from which the local cliques are formed.
    delta : float
        Chordal distance on the Riemann sphere under which points pair (Möbius term).
    max_iter : int
        Subgradient iterations of the sparse stage's dual decomposition.
    dense_max_iter : int
        Sweeps of the dense stage's block-coordinate dual ascent (it stops earlier when the
        duality gap is below 1e-3), or its subgradient iterations with
        ``dense_one_to_one``.
    dense_one_to_one : bool
        Keep the paper's one-to-one constraint in the dense stage (default False: several
        vertices of A may take one vertex of B; see :mod:`medseg.matching._dense`).
    refine : bool
        Polish the dense map with :func:`spectral_refine` (ZoomOut), an addition to the
        paper's pipeline. Default True.
    dense_stage : bool
        Minimise the paper's dense energy over every vertex's candidates (True), or give
        each vertex its cheapest candidate (False, the default). Off by default because,
        once refined, its maps are no better than the candidates' (but for which solve is
        kept on a few human bodies, a fragile choice either way) and it costs about a sixth
        of the time: 10 FAUST and 10 TOSCA pairs in one run (``benchmarks/bench_matching.py
        --methods medseg medseg-dense``, 2026-12-06) scored 0.054 / 0.035 mean direct error
        without it and 0.040 / 0.037 with it, in 0.83 / 0.86 of its CPU time. The FAUST
        difference is one pair where both maps are wrong (tr_reg_069 -> tr_reg_077, 0.35
        against 0.21: a solve's mirrored fraction sits at ``max_mirrored``, 0.52 against
        0.5); on the other 19 pairs the two agree within 0.004 but for TOSCA cat3 -> cat7,
        0.038 without the stage against 0.049. Two earlier 50 + 50 pair runs refined the
        candidates alone as well as the dense maps (0.054 / 0.039 against 0.055 / 0.041;
        0.028 / 0.042 against 0.032 / 0.044). On the 50 FAUST pairs of the latter, without
        the stage (2026-12-06): 0.042 against 0.032, the choice among solves wrong on two
        pairs in each run but not the same ones (0.51 and 0.35 against 0.17 and 0.21), the
        other 47 within 0.01. On strongly non-isometric pairs (``bench_matching_variants.py
        --variant deformed``, 20 FAUST pairs) the stage, whose edge-length term assumes an
        isometry, costs accuracy: mean error 0.23 without it, 0.33 with it (pyfmaps 0.40);
        on partial ones (``--variant partial``, 10 pairs, 20 % of one body cut away, where
        its "unmatched" label tells the refinement which vertices to fit) 0.23 without it,
        0.39 with it (pyfmaps 0.34).
    n_solves : int
        Sparse solves, each followed by its own dense matching and refinement. Every solve
        after the first excludes the matches of the earlier ones, so that it settles in
        another basin of the symmetric ambiguity (HKS and WKS cannot tell left from right,
        and on humans hardly front from back). Of the maps that are not mirrored, the one
        closest to an isometry (lowest :func:`spectral_residual`) is returned. 1 turns this
        off; see Notes.
    max_mirrored : float
        A map whose :func:`mirrored_fraction` exceeds this is a left-right (or front-back)
        flip and is returned only if every solve gave one (then the least mirrored).
    exclude_radius : float
        In a later solve, each sparse point's candidates exclude the targets within this
        geodesic distance (units of ``sqrt(area)``) of its earlier matches.
    partial : bool
        One surface may be only part of the other (a limb cut away, an occluded scan). Both
        must then be in the same units: they are scaled by the larger one's ``sqrt(area)``
        (not each to unit area); samples avoid the boundary of a surface with holes; the
        refinement fits its functional maps on the vertices the dense stage matched (with
        ``dense_stage``, else on all); and the result says what has no partner: a map back
        from B to A is computed as the forward one is; ``forward`` is -1 on the vertices of
        A that it does not come near (``matched`` False), and ``inverse`` (the map back) on
        the vertices of B that the forward map does not come near. Not reliable yet: with
        20 % of one FAUST body cut away (``benchmarks/bench_matching_variants.py``) the sparse
        stage often matches the lost part's points elsewhere (mean error 0.23 over 10 pairs,
        pyfmaps 0.34).
    random_state : int, RandomState or None
        Farthest-point seeds and the clique sampling.
    progress : bool
        Show tqdm progress of the solvers.

    Returns
    -------
    SurfaceMatch

    Notes
    -----
    Where this differs from the paper, and why:

    * The sparse stage: see :mod:`medseg.matching._sparse` (descriptor, targets, cliques,
      geodesic and intrinsic orientation terms, each with the measurement that motivated
      it).
    * Units: each surface is centred and scaled to unit area before anything else, so A
      and B may come in different units (mm and m) without any option; distances in the
      options are in units of ``sqrt(area)``.
    * The dense stage runs only when asked for (``dense_stage``):
      without it each vertex takes its cheapest Möbius-vote candidate, and the spectral
      refinement that follows gives maps as good (see ``dense_stage``).
    * Dense stage cliques are the faces of A. For a face and a label triplet the third-order
      cost is the squared edge-length distortion (in mean edge lengths) plus
      ``lambda_gauss`` if the image triangle is mirrored against B's normals: a Möbius
      residual per face and label combination would cost ``F (K+1)^3`` alignments.
    * The dense stage drops the one-to-one constraint by default (two independent
      remeshings have no vertex bijection, and with it the stage's duality gap stayed near
      0.45: :mod:`medseg.matching._dense`), and is solved by block-coordinate dual ascent to
      a certified gap; ``dense_one_to_one=True`` restores it. A vertex may stay unmatched;
      it then takes its best dense candidate, so ``forward`` is complete.
    * Each Möbius vote is weighted, per vertex, by how well the same map carries the nearby
      matched sparse points (a conformal map fixed by one triplet is accurate only near it).
    * ``refine=True`` adds a ZoomOut pass (iterated on 1,000 samples per surface, the last
      step on every vertex); ``forward_unrefined`` keeps the map without it.
    * ``n_solves=2`` solves the sparse stage a second time, without the first solution's
      matches, and keeps one of the two maps (not mirrored, lowest spectral residual): on
      bodies with a left-right symmetry the lowest sparse energy is not a reliable guide
      (:mod:`medseg.matching._matcher`, "Mirror flips"). It doubles everything after
      :func:`prepare_surface`.

    References
    ----------
    .. [1] Zeng, Y., Wang, C., Wang, Y., Gu, X., Samaras, D. & Paragios, N. "Dense non-rigid
       surface registration using high-order graph matching." CVPR 2010.
       doi:10.1109/CVPR.2010.5540189
    .. [2] Lipman, Y. & Funkhouser, T. "Möbius voting for surface correspondence." ACM TOG
       28(3), 2009. doi:10.1145/1531326.1531378
    """
    if n_sparse < 4 or n_sparse_targets < n_sparse or n_candidates < 1:
        raise ProblemDefinitionError(
            "need n_sparse >= 4, n_sparse_targets >= n_sparse and n_candidates >= 1."
        )
    if orientation not in ("intrinsic", "normals"):
        raise ProblemDefinitionError(
            f"orientation must be 'intrinsic' or 'normals', got {orientation!r}."
        )
    if not 0.0 <= max_mirrored <= 1.0 or n_solves < 1 or not exclude_radius > 0:
        raise ProblemDefinitionError(
            "need 0 <= max_mirrored <= 1, n_solves >= 1 and exclude_radius > 0, got "
            f"{max_mirrored}, {n_solves} and {exclude_radius}."
        )
    if n_neighbours < 2:
        raise ProblemDefinitionError(f"n_neighbours must be at least 2, got {n_neighbours}.")
    rng = check_random_state(random_state)
    opts = {
        "partial": partial,
        "lambda_descriptor": lambda_descriptor,
        "lambda_mobius": lambda_mobius,
        "lambda_gauss": lambda_gauss,
        "lambda_geodesic": lambda_geodesic,
        "orientation": orientation,
        "n_neighbours": n_neighbours,
        "delta": delta,
        "max_iter": max_iter,
        "dense_max_iter": dense_max_iter,
        "dense_one_to_one": dense_one_to_one,
        "exclude_radius": exclude_radius,
        "progress": progress,
    }
    timings = {}
    bar = tqdm(total=5, desc="matching", disable=not progress, leave=False)
    t0 = time.perf_counter()
    n_s = max(n_align, n_sparse_targets)
    unit = None
    if partial:  # one scale for both: the part keeps its size relative to the whole
        va, fa = check_mesh(vertices_a, faces_a, name="surface A")
        vb, fb = check_mesh(vertices_b, faces_b, name="surface B")
        areas = face_areas(va, fa).sum(), face_areas(vb, fb).sum()
        unit = float(np.sqrt(max(areas)))
    a = prepare_surface(
        vertices_a, faces_a, name="surface A", n_samples=n_s, scale=unit, random_state=rng
    )
    b = prepare_surface(
        vertices_b, faces_b, name="surface B", n_samples=n_s, scale=unit, random_state=rng
    )
    timings["prepare"] = time.perf_counter() - t0
    bar.update(1)
    mass_a = vertex_areas(a.vertices, a.faces)
    attempts = []
    for attempt in range(n_solves):
        att = _attempt(
            a,
            b,
            exclude=[t["targets"] for t in attempts],
            n_sparse=n_sparse,
            n_sparse_targets=n_sparse_targets,
            n_candidates=n_candidates,
            n_triplets=n_triplets,
            n_align=n_align,
            n_vote=n_vote,
            n_modes=n_modes,
            mode_radius=mode_radius,
            refine=refine,
            dense=bool(dense_stage),
            mass_a=mass_a,
            opts=opts,
            rng=rng,
        )
        for step, sec in att["timings"].items():
            timings[step] = timings.get(step, 0.0) + sec
        attempts.append(att)
        bar.update(4 if attempt == 0 else 0)
    bar.close()
    best = attempts[
        _choose_solve(
            [t["mirrored"] for t in attempts],
            [t["spectral"] for t in attempts],
            max_mirrored=max_mirrored,
        )
    ]
    forward = best["forward"].copy()
    _, inverse = cKDTree(b.vertices[forward]).query(b.vertices)
    matched = np.ones(len(forward), dtype=bool)
    if partial:
        inverse, matched, covered_b = best["cover"]
        forward[~matched] = -1
        inverse[~covered_b] = -1
    return SurfaceMatch(
        forward=forward,
        matched=matched,
        forward_unrefined=best["unrefined"],
        forward_votes=best["voted"],
        inverse=np.asarray(inverse, dtype=np.int64),
        sparse_pairs=best["pairs"],
        sparse=best["sparse"],
        dense=best["dense"],
        matched_fraction=np.nan if best["dense"] is None else float(np.mean(best["matched"])),
        mirrored_fraction=best["mirrored"],
        solves=[
            {
                "forward": t["forward"],
                "unrefined": t["unrefined"],
                "mirrored": t["mirrored"],
                "spectral": t["spectral"],
                "residual": t["residual"],
                "energy": t["sparse"].energy,
            }
            for t in attempts
        ],
        timings=timings,
    )
