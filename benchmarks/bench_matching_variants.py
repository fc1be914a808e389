"""Surface matching beyond near-isometry: strongly non-isometric pairs and partial surfaces.

Both variants are built here, from the pairs of ``bench_matching.py`` (FAUST or TOSCA test
pairs, the same seeded subset), deterministically (``--seed`` and the pair's position),
and never stored: the meshes in the data folder are only read.

``--variant deformed`` (non-isometric). B is deformed by large local scalings:

* its five extremities (the first five geodesic farthest-point samples: hands, feet and head
  on FAUST) each carry a region of geodesic radius ``0.3 sqrt(area)``, scaled about the
  centroid of the region's boundary ring (where it attaches) by a factor drawn with
  ``log s`` uniform in ``+-[log 1.25, log 1.5]`` (limbs stretched or shrunk, lengths and
  thickness alike: their areas change by factors of 0.44-0.64 or 1.56-2.25);
* the torso (geodesic radius ``0.25 sqrt(area)`` around the vertex nearest to the
  centroid) is thickened: its points move away from the region's principal axis by a factor
  drawn in ``[1.15, 1.35]``;
* every region's weight falls smoothly (smoothstep) to 0 over ``0.1 sqrt(area)`` at its
  edge: ``x' = x + sum_k w_k(x) (s_k - 1) (x - p_k)`` (``p_k`` the attachment point, or for
  the torso the point's projection on the axis). If a face degenerates, all factors are
  pulled towards 1 by 0.8 in log and the deformation is rebuilt.

Connectivity is untouched, so the ground truth of the pair still holds; the vertex order of
B was already unrelated to A's (every shape was remeshed independently). Geodesic errors
are measured on the deformed B, over its ``sqrt(area)``.

``--variant partial``. One extremity of B (``--cut b``, default) or of A (``--cut a``),
drawn among the five, is cut away with the faces within the geodesic radius from its tip
that removes 20 % of the area (the largest connected component is kept). The pair is matched
with ``match_surfaces(..., partial=True)``. Scored on the rows whose two vertices both
remain (the part that has a partner): mean error over the rows medseg matched, the % within
0.05 over all rows with a partner (a row medseg leaves unmatched never counts as within),
and how well medseg says what has no partner: ``cut b``: the share of A's rows whose
partner was cut that it leaves unmatched (``unmatched_right``) and of the rows with a
partner that it leaves unmatched (``unmatched_wrong``); ``cut a``: the same for B's rows in
the inverse map. Errors are over ``sqrt(area)`` of the uncut B, geodesics on the (cut) B.
pyfmaps matches every vertex; it is scored on the same rows.

Usage::

    python benchmarks/bench_matching_variants.py --variant deformed --n-pairs 20 --out /tmp/v
    python benchmarks/bench_matching_variants.py --variant partial --n-pairs 20 --out /tmp/p
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from medseg.errors import MeshError
from medseg.geometry import GeodesicSolver, face_areas, geodesic_farthest_point_sampling
from medseg.matching import check_mesh, match_surfaces, read_mesh, write_mesh
from medseg.matching._scoring import geodesic_errors, read_vts

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_matching import THRESHOLDS, _default_data, _pyfmaps  # noqa: E402

N_EXTREMITIES = 5


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _extremities(v, f, geo, rng) -> np.ndarray:
    return geodesic_farthest_point_sampling(v, f, N_EXTREMITIES, geodesic=geo, random_state=rng)


def deform(v: np.ndarray, f: np.ndarray, rng: np.random.RandomState) -> tuple[np.ndarray, dict]:
    """B with limbs scaled and the torso thickened (see the module docstring)."""
    unit = np.sqrt(face_areas(v, f).sum())
    geo = GeodesicSolver(v, f)
    tips = _extremities(v, f, geo, rng)
    radius, fall = 0.3 * unit, 0.1 * unit
    log_s = rng.uniform(np.log(1.25), np.log(1.5), N_EXTREMITIES)
    log_s *= rng.choice([-1, 1], N_EXTREMITIES)
    torso_s = rng.uniform(1.15, 1.35)
    regions = []
    for tip in tips:
        d = geo.distance(tip)
        ring = np.abs(d - radius) < 0.02 * unit
        attach = v[ring].mean(axis=0) if ring.any() else v[tip]
        w = _smoothstep((radius + fall / 2 - d) / fall)
        regions.append((w, v - attach))
    centre = int(np.argmin(((v - v.mean(axis=0)) ** 2).sum(axis=1)))
    d0 = geo.distance(centre)
    w0 = _smoothstep((0.25 * unit + fall / 2 - d0) / fall)
    core = v[d0 < 0.25 * unit]
    mid = core.mean(axis=0)
    axis = np.linalg.svd(core - mid, full_matrices=False)[2][0]
    rel = v - mid
    radial = rel - np.outer(rel @ axis, axis)  # from the torso's axis
    shrink = 1.0
    for _ in range(10):
        scales = np.exp(shrink * log_s)
        t_scale = np.exp(shrink * np.log(torso_s))
        out = v + (t_scale - 1) * w0[:, None] * radial
        for (w, offset), s in zip(regions, scales, strict=True):
            out = out + (s - 1) * w[:, None] * offset
        try:
            check_mesh(out, f)
            break
        except MeshError:
            shrink *= 0.8
    else:
        raise MeshError("could not deform this mesh without degenerating a face")
    return out, {"limb_scales": scales.round(3).tolist(), "torso_scale": round(float(t_scale), 3)}


def _largest_component(n: int, faces: np.ndarray) -> np.ndarray:
    e = np.vstack([faces[:, [0, 1]], faces[:, [1, 2]]])
    g = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    big = np.bincount(comp[faces[:, 0]]).argmax()
    return faces[comp[faces[:, 0]] == big]


def _pinched(faces: np.ndarray) -> np.ndarray:
    """Vertices where the boundary touches itself (more than two boundary edges)."""
    half = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    n = int(faces.max()) + 1
    alone = ~np.isin(half[:, 0] * n + half[:, 1], half[:, 1] * n + half[:, 0])
    count = np.bincount(half[alone].ravel(), minlength=n)
    return np.flatnonzero(count > 2)


def cut(v: np.ndarray, f: np.ndarray, rng: np.random.RandomState, fraction: float = 0.2):
    """Remove one extremity with ``fraction`` of the area; returns the cut mesh, the new
    index of every old vertex (-1: removed) and what was done.

    The faces whose three vertices lie within a geodesic radius of the extremity's tip go,
    the radius chosen so that they carry ``fraction`` of the area; then the largest
    connected component is kept, and the faces at any vertex where the boundary touches
    itself are removed until the boundary is a set of simple loops."""
    geo = GeodesicSolver(v, f)
    tip = _extremities(v, f, geo, rng)[rng.randint(N_EXTREMITIES)]
    d = geo.distance(tip)
    far = d[f].max(axis=1)  # a face goes when all its vertices are within the radius
    order = np.argsort(far)
    area = face_areas(v, f)
    n_cut = int(np.searchsorted(np.cumsum(area[order]), fraction * area.sum()))
    keep = np.ones(len(f), dtype=bool)
    keep[order[:n_cut]] = False
    faces = _largest_component(len(v), f[keep])
    for _ in range(20):
        bad = _pinched(faces)
        if not len(bad):
            break
        faces = _largest_component(len(v), faces[~np.isin(faces, bad).any(axis=1)])
    used = np.unique(faces)
    new = np.full(len(v), -1, dtype=np.int64)
    new[used] = np.arange(len(used))
    info = {
        "tip": int(tip),
        "cut_area": float(1 - face_areas(v[used], new[faces]).sum() / area.sum()),
    }
    return v[used], new[faces], new, info


def _curve(err: np.ndarray, ok: np.ndarray) -> list[float]:
    """Fraction of rows within each threshold; rows not ``ok`` (unmatched) never are."""
    return [float(np.mean((err <= t) & ok)) for t in THRESHOLDS]


def run(args: argparse.Namespace) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "pairs.jsonl"
    rng = np.random.RandomState(args.seed)
    jobs = []
    for name in args.sets:
        folder = Path(args.data) / name
        pairs = [ln.split() for ln in (folder / "test_pairs.txt").read_text().splitlines() if ln]
        pick = rng.permutation(len(pairs))[: args.n_pairs]
        jobs += [(name, i, *pairs[j]) for i, j in enumerate(pick)]
    done = set()
    if log.exists():
        done = {(r["set"], r["a"], r["b"]) for r in map(json.loads, log.read_text().splitlines())}
    for set_name, index, a, b in jobs:
        if (set_name, a, b) in done:
            continue
        folder = Path(args.data) / set_name
        va, fa = check_mesh(*read_mesh(folder / f"{a}.off"))
        vb, fb = check_mesh(*read_mesh(folder / f"{b}.off"))
        gt_a, gt_b = (read_vts(folder / "corres" / f"{n}.vts") for n in (a, b))
        pair_rng = np.random.RandomState([args.seed, index, len(set_name)])
        unit_b = np.sqrt(face_areas(vb, fb).sum())
        info = {}
        if args.variant == "deformed":
            vb, info = deform(vb, fb, pair_rng)
            partial = False
            has = np.ones(len(gt_a), dtype=bool)
            unit_b = np.sqrt(face_areas(vb, fb).sum())
        else:
            partial = True
            if args.cut == "b":
                vb, fb, new, info = cut(vb, fb, pair_rng)
                gt_b = new[gt_b]
            else:
                va, fa, new, info = cut(va, fa, pair_rng)
                gt_a = new[gt_a]
            has = (gt_a >= 0) & (gt_b >= 0)
        maps, seconds, extra = {}, {}, {}
        with tempfile.TemporaryDirectory() as tmp:
            pa, pb = Path(tmp) / "a.off", Path(tmp) / "b.off"
            write_mesh(pa, va, fa)
            write_mesh(pb, vb, fb)
            if "medseg" in args.methods:
                t0 = time.perf_counter()
                res = match_surfaces(va, fa, vb, fb, partial=partial, random_state=args.seed)
                seconds["medseg"] = time.perf_counter() - t0
                maps["medseg"] = res.forward
                gap = float("nan") if res.dense is None else res.dense.gap
                extra = {"dense_gap": gap, "timings": res.timings}
                extra["solves"] = [
                    {k: v for k, v in sv.items() if k not in ("forward", "unrefined")}
                    for sv in res.solves
                ]
                for i, sv in enumerate(res.solves):  # each solve's own map, for the choice
                    maps[f"medseg-solve{i}"] = sv["forward"]
                    seconds[f"medseg-solve{i}"] = float("nan")
                if partial:
                    extra["inverse"] = res.inverse
            if "pyfmaps" in args.methods:
                t0 = time.perf_counter()
                maps["pyfmaps"] = _pyfmaps(pa, pb)
                seconds["pyfmaps"] = time.perf_counter() - t0
        geo = GeodesicSolver(vb, fb)
        rows = np.flatnonzero(has)
        scores = {}
        for name, fwd in maps.items():
            img = fwd[gt_a[rows]]
            ok = img >= 0
            err = np.full(len(rows), np.inf)
            if ok.any():
                err[ok] = geodesic_errors(vb, fb, gt_b[rows][ok], img[ok], geodesic=geo)
                err[ok] *= np.sqrt(face_areas(vb, fb).sum()) / unit_b
            sc = {
                "mean_matched": float(err[ok].mean()) if ok.any() else float("nan"),
                "matched_rows": float(ok.mean()),
                "curve": _curve(err, ok),
                "seconds": seconds[name],
            }
            if partial and name == "medseg":  # what it says has no partner
                if args.cut == "b":
                    lost = (gt_a >= 0) & (gt_b < 0)
                    unmatched = fwd[np.maximum(gt_a, 0)] < 0
                else:
                    lost = (gt_b >= 0) & (gt_a < 0)
                    unmatched = extra["inverse"][np.maximum(gt_b, 0)] < 0
                sc["unmatched_right"] = float(unmatched[lost].mean()) if lost.any() else None
                sc["unmatched_wrong"] = float(unmatched[has].mean())
            scores[name] = sc
        extra.pop("inverse", None)
        record = {"set": set_name, "a": a, "b": b, "variant": args.variant, "build": info}
        record.update(scores=scores, medseg_info=extra)
        with open(log, "a") as fh:
            fh.write(json.dumps(record) + "\n")
        print(
            f"{set_name} {a}->{b} {info}: "
            + ", ".join(
                f"{n} {s['mean_matched']:.3f}/{s['seconds']:.0f}s" for n, s in scores.items()
            ),
            file=sys.stderr,
        )


def summarise(args: argparse.Namespace) -> None:
    recs = [json.loads(ln) for ln in (Path(args.out) / "pairs.jsonl").read_text().splitlines()]
    print(
        "set  method  pairs  mean-err(matched)  matched-rows  <=0.025  <=0.05  <=0.1  s/pair"
        "  unmatched right / wrong"
    )
    for set_name in sorted({r["set"] for r in recs}):
        rs = [r for r in recs if r["set"] == set_name]
        methods = set.intersection(*(set(r["scores"]) for r in rs))
        for m in sorted(methods):
            s = [r["scores"][m] for r in rs]
            curve = np.mean([x["curve"] for x in s], axis=0)
            line = (
                f"{set_name}  {m}  {len(s)}  {np.nanmean([x['mean_matched'] for x in s]):.4f}  "
                f"{np.mean([x['matched_rows'] for x in s]):.3f}  "
                + "  ".join(f"{curve[THRESHOLDS.index(t)]:.3f}" for t in (0.025, 0.05, 0.1))
                + f"  {np.mean([x['seconds'] for x in s]):.1f}"
            )
            if "unmatched_wrong" in s[0]:
                right = [x["unmatched_right"] for x in s if x["unmatched_right"] is not None]
                line += f"  {np.mean(right):.3f} / {np.mean([x['unmatched_wrong'] for x in s]):.3f}"
            print(line)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variant", choices=["deformed", "partial"], required=True)
    parser.add_argument("--cut", choices=["a", "b"], default="b", help="partial: which surface")
    parser.add_argument("--data", default=str(_default_data()), help="shapes folder")
    parser.add_argument("--sets", nargs="+", default=["FAUST"])
    parser.add_argument("--methods", nargs="+", default=["medseg", "pyfmaps"])
    parser.add_argument("--n-pairs", type=int, default=20, help="pairs per set (default 20)")
    parser.add_argument("--seed", type=int, default=0, help="pairs, deformations and matcher")
    parser.add_argument("--out", default="/tmp/bench_matching_variants", help="results folder")
    parser.add_argument("--summarise", action="store_true", help="only print the summary")
    args = parser.parse_args(argv)
    if not args.summarise:
        run(args)
    summarise(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
