"""Benchmark of the surface matcher against a functional-map baseline on FAUST / TOSCA.

Protocol (``data/shapes/README.md``, Kim, Lipman & Funkhouser 2011): for a map T from A to
B and each ground-truth row i, ``err_i = geodesic_B(T(A.vts[i]), B.vts[i]) / sqrt(area(B))``
with heat-method geodesics on B (:func:`medseg.matching._scoring.geodesic_errors`); the mean
over rows and pairs, the fraction of rows with ``err <= t`` for a few thresholds, direct and
symmetry-aware (per pair, the better of the direct and the mirrored ground truth). Also the
log area ratio of matched facets (mean ``|log(area(T(f)) / area(f))|`` on unit-area surfaces,
over faces whose image is not degenerate, plus the fraction of degenerate images).

Methods, all in the same run on the same pairs:

* ``medseg``: :func:`medseg.matching.match_surfaces` (default options: no dense stage, with
  the spectral refinement);
* ``medseg-norefine``: the same run's map before the refinement (each vertex on its best
  dense candidate: the sparse stage and the Möbius votes alone);
* ``medseg-solve<i>``: the map of each sparse solve (the choice among them);
* ``medseg-dense`` (only when asked for in ``--methods``): the matcher with the paper's
  dense stage (``dense_stage=True``), timed on its own, and ``medseg-dense-norefine`` its
  map before the refinement (the paper's pipeline alone); its duality gaps are the ones
  the summary reports. With ``medseg`` and ``medseg-norefine`` that is the ablation: the
  votes alone, with the dense stage, each with and without the refinement;
* ``pyfmaps``: functional maps with WKS descriptors, orientation term and ZoomOut (pyfmaps
  1.3.1, an optional benchmark-only dependency: ``pip install pyfmaps==1.3.1``).

Pairs: a fixed random subset (``--n-pairs``, ``--seed``) of each set's ``test_pairs.txt``.
Results are appended to ``<out>/pairs.jsonl`` as each pair finishes (a time-boxed run still
leaves usable numbers; ``--resume`` skips, per method, pairs that method already scored, so
``--methods pyfmaps`` and ``--methods medseg`` may fill the same file in separate runs);
``--summarise`` prints the aggregate table from that file (the latest score of each pair and
method, over the pairs of each set that every method scored unless ``--all-pairs``). Each
score records wall time and the process's CPU time (shared machine).

A map is counted as *flipped* when its error against the mirrored ground truth is less than
half its error against the true one (the symmetry-aware score picks the mirror by a clear
margin). The summary gives flips per 100 pairs, medseg's dense-stage duality gaps, and the
ratio of medseg's time per pair to pyfmaps' on the pairs both scored.

Usage::

    python benchmarks/bench_matching.py --n-pairs 50 --out /tmp/bench_matching
    python benchmarks/bench_matching.py --out /tmp/bench_matching --summarise
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from itertools import zip_longest
from pathlib import Path

import numpy as np

from medseg.geometry import GeodesicSolver, face_areas
from medseg.matching import match_surfaces, read_mesh
from medseg.matching._scoring import geodesic_errors, read_vts

THRESHOLDS = (0.0, 0.025, 0.05, 0.075, 0.1, 0.15, 0.2, 0.25)
SETS = ("FAUST", "TOSCA_Isometric")


def _default_data() -> Path:
    env = os.environ.get("MEDSEG_DATA")
    root = Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data"
    return root / "shapes"


def _pyfmaps(path_a: Path, path_b: Path) -> np.ndarray:
    from pyFM.functional import FunctionalMapping
    from pyFM.mesh import TriMesh

    mesh_a, mesh_b = TriMesh.load(str(path_a)), TriMesh.load(str(path_b))
    model = FunctionalMapping(mesh_b, mesh_a)  # get_p2p: vertices of A -> vertices of B
    model.preprocess(n_descr=100, descr_type="WKS", k_process=200, subsample_step=5, verbose=False)
    model.fit(K=(35, 35), w_descr=1, w_lap=1e-2, w_dcomm=1e-1, w_orient=1, verbose=False)
    fmap = model.zoomout_refine(nit=15, step=10, verbose=False)
    return np.asarray(model.get_p2p(FM=fmap), dtype=np.int64)


def _log_area_ratio(va, fa, vb, fb, forward) -> tuple[float, float]:
    area_a = face_areas(va, fa) / face_areas(va, fa).sum()
    area_b = face_areas(vb[forward], fa) / face_areas(vb, fb).sum()
    ok = area_b > 1e-12
    return float(np.mean(np.abs(np.log(area_b[ok] / area_a[ok])))), float(1 - ok.mean())


def _score(vb, fb, gt_a, gt_b, gt_sym, maps: dict) -> dict:
    if not maps:
        return {}
    geo = GeodesicSolver(vb, fb)
    images = np.stack([fwd[gt_a] for fwd in maps.values()])
    direct, sym = (
        dict(zip(maps, geodesic_errors(vb, fb, gt, images, geodesic=geo), strict=True))
        for gt in (gt_b, gt_sym)
    )
    result = {}
    for name in maps:
        d, s = direct[name], sym[name]
        best = s if s.mean() < d.mean() else d
        result[name] = {
            "direct_mean": float(d.mean()),
            "sym_mean": float(best.mean()),
            "mirror_mean": float(s.mean()),
            "flipped": bool(s.mean() < 0.5 * d.mean()),
            "direct_curve": [float(np.mean(d <= t)) for t in THRESHOLDS],
            "sym_curve": [float(np.mean(best <= t)) for t in THRESHOLDS],
        }
    return result


def _scored(log: Path) -> set:
    """(set, a, b, method) already in the log."""
    if not log.exists():
        return set()
    return {
        (r["set"], r["a"], r["b"], m)
        for r in map(json.loads, log.read_text().splitlines())
        for m in r["scores"]
    }


def run(args: argparse.Namespace) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "pairs.jsonl"
    rng = np.random.RandomState(args.seed)
    per_set = []
    for name in args.sets:
        folder = Path(args.data) / name
        pairs = [ln.split() for ln in (folder / "test_pairs.txt").read_text().splitlines() if ln]
        pick = rng.permutation(len(pairs))[: args.n_pairs]
        per_set.append([(name, *pairs[i]) for i in pick])
    # interleave the sets so a time-boxed run covers both
    jobs = [job for group in zip_longest(*per_set) for job in group if job is not None]
    if args.reverse:  # a second process can work from the other end into the same file
        jobs = jobs[::-1]
    deadline = time.time() + 60 * args.minutes if args.minutes else np.inf
    for set_name, a, b in jobs:
        done = _scored(log) if args.resume else set()
        methods = [m for m in args.methods if (set_name, a, b, m) not in done]
        if not methods:
            continue
        if time.time() > deadline:
            print("time budget reached; stopping", file=sys.stderr)
            break
        folder = Path(args.data) / set_name
        pa, pb = folder / f"{a}.off", folder / f"{b}.off"
        va, fa = read_mesh(pa)
        vb, fb = read_mesh(pb)
        gt_a, gt_b, gt_sym = (
            read_vts(folder / "corres" / f"{name}.vts") for name in (a, b, f"{b}.sym")
        )
        maps, seconds, cpu, extra = {}, {}, {}, {}
        if "medseg" in methods:
            t0, c0 = time.perf_counter(), time.process_time()
            res = match_surfaces(va, fa, vb, fb, random_state=args.seed)
            seconds["medseg"] = time.perf_counter() - t0
            cpu["medseg"] = time.process_time() - c0
            seconds["medseg-norefine"] = seconds["medseg"] - res.timings.get("refine", 0.0)
            cpu["medseg-norefine"] = np.nan
            maps["medseg"], maps["medseg-norefine"] = res.forward, res.forward_unrefined
            # each sparse solve's own map, to study the choice among them (no extra CPU)
            for i, solve in enumerate(res.solves):
                maps[f"medseg-solve{i}"] = solve["forward"]
                seconds[f"medseg-solve{i}"] = cpu[f"medseg-solve{i}"] = np.nan
            if args.save_maps:
                solves = res.solves
                (out / "maps").mkdir(exist_ok=True)
                np.savez_compressed(
                    out / "maps" / f"{set_name}_{a}_{b}.npz",
                    **{name.replace("-", "_"): fwd for name, fwd in maps.items()},
                    **{f"medseg_solve{i}_unrefined": t["unrefined"] for i, t in enumerate(solves)},
                )
            extra = {
                "sparse_gap": res.sparse.gap,
                "dense_gap": np.nan if res.dense is None else res.dense.gap,
                "matched": res.matched_fraction,
                "solves": [
                    {k: v for k, v in solve.items() if k not in ("forward", "unrefined")}
                    for solve in res.solves
                ],
                "timings": res.timings,
            }
        if "medseg-dense" in methods:
            t0, c0 = time.perf_counter(), time.process_time()
            res = match_surfaces(va, fa, vb, fb, random_state=args.seed, dense_stage=True)
            seconds["medseg-dense"] = time.perf_counter() - t0
            cpu["medseg-dense"] = time.process_time() - c0
            maps["medseg-dense"], maps["medseg-dense-norefine"] = res.forward, res.forward_unrefined
            seconds["medseg-dense-norefine"] = cpu["medseg-dense-norefine"] = np.nan
            extra = extra | {"dense_gap": res.dense.gap, "dense_timings": res.timings}
        if "pyfmaps" in methods:
            t0, c0 = time.perf_counter(), time.process_time()
            maps["pyfmaps"] = _pyfmaps(pa, pb)
            seconds["pyfmaps"] = time.perf_counter() - t0
            cpu["pyfmaps"] = time.process_time() - c0
        scores = _score(vb, fb, gt_a, gt_b, gt_sym, maps)
        for name, fwd in maps.items():
            scores[name]["seconds"] = seconds[name]
            scores[name]["cpu_seconds"] = cpu[name]
            scores[name]["log_area_ratio"], scores[name]["degenerate"] = _log_area_ratio(
                va, fa, vb, fb, fwd
            )
        record = {"set": set_name, "a": a, "b": b, "scores": scores, "medseg_info": extra}
        with open(log, "a") as fh:
            fh.write(json.dumps(record) + "\n")
        print(
            f"{set_name} {a}->{b}: "
            + ", ".join(
                f"{n} {s['direct_mean']:.3f}/{s['seconds']:.0f}s" for n, s in scores.items()
            ),
            file=sys.stderr,
        )


def summarise(args: argparse.Namespace) -> None:
    lines = (Path(args.out) / "pairs.jsonl").read_text().splitlines()
    scores = {}  # (set, method) -> {(a, b): latest score}
    info = {}  # (set, a, b) -> medseg_info of the latest medseg run
    for r in map(json.loads, lines):
        for method, sc in r["scores"].items():
            scores.setdefault((r["set"], method), {})[(r["a"], r["b"])] = sc
        if r.get("medseg_info"):
            info[(r["set"], r["a"], r["b"])] = r["medseg_info"]
    if not args.all_pairs:  # compare the methods on the pairs all of them scored
        for set_name in {k[0] for k in scores}:
            keys = [k for k in scores if k[0] == set_name]
            common = set.intersection(*(set(scores[k]) for k in keys))
            for k in keys:
                scores[k] = {pair: sc for pair, sc in scores[k].items() if pair in common}
    header = "set  method  pairs  direct  sym  " + "  ".join(f"<={t}" for t in THRESHOLDS[1:])
    print(header + "  flips/100  log-area  s/pair  cpu-s/pair")
    for (set_name, method), per_pair in sorted(scores.items()):
        s = list(per_pair.values())
        if not s:
            continue
        curve = np.mean([x["direct_curve"] for x in s], axis=0)
        cpu = np.array([np.nan if x.get("cpu_seconds") is None else x["cpu_seconds"] for x in s])
        cpu = np.nanmean(cpu) if np.isfinite(cpu).any() else np.nan
        # flipped: the mirrored truth fits better by a clear margin (sym_mean is the better
        # of the two, so records without mirror_mean count alike)
        flips = 100 * np.mean([x["sym_mean"] < 0.5 * x["direct_mean"] for x in s])
        print(
            f"{set_name}  {method}  {len(s)}  {np.mean([x['direct_mean'] for x in s]):.4f}  "
            f"{np.mean([x['sym_mean'] for x in s]):.4f}  "
            + "  ".join(f"{c:.3f}" for c in curve[1:])
            + f"  {flips:.0f}  {np.mean([x['log_area_ratio'] for x in s]):.3f}"
            + f"  {np.mean([x['seconds'] for x in s]):.1f}  {cpu:.1f}"
        )
    for set_name in sorted({k[0] for k in scores}):
        ms, pf = scores.get((set_name, "medseg"), {}), scores.get((set_name, "pyfmaps"), {})
        both = sorted(set(ms) & set(pf))
        if both:
            t_ms = np.array([ms[p]["seconds"] for p in both])
            t_pf = np.array([pf[p]["seconds"] for p in both])
            print(
                f"{set_name}: medseg / pyfmaps time per pair {t_ms.mean() / t_pf.mean():.2f} "
                f"(mean of per-pair ratios {np.mean(t_ms / t_pf):.2f}, {len(both)} pairs)"
            )
        gaps = [info[(set_name, *p)] for p in ms if (set_name, *p) in info]
        if gaps:
            sparse = np.array([g["sparse_gap"] for g in gaps])
            print(
                f"{set_name}: sparse-stage gap mean {sparse.mean():.4f} max {sparse.max():.4f} "
                f"({len(gaps)} pairs)"
            )
            dense = np.array([g.get("dense_gap", np.nan) for g in gaps], dtype=float)
            dense = dense[np.isfinite(dense)]
            if dense.size:
                print(
                    f"{set_name}: dense-stage gap mean {dense.mean():.4f} median "
                    f"{np.median(dense):.4f} max {dense.max():.4f} ({dense.size} pairs)"
                )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=str(_default_data()), help="shapes folder")
    parser.add_argument("--sets", nargs="+", default=list(SETS))
    parser.add_argument("--methods", nargs="+", default=["medseg", "pyfmaps"])
    parser.add_argument("--n-pairs", type=int, default=50, help="pairs per set (default 50)")
    parser.add_argument("--seed", type=int, default=0, help="pair subset and matcher seed")
    parser.add_argument("--minutes", type=float, default=0, help="time budget (0: none)")
    parser.add_argument("--out", default="/tmp/bench_matching", help="results folder")
    parser.add_argument("--resume", action="store_true", help="skip pairs already scored")
    parser.add_argument("--summarise", action="store_true", help="only print the summary")
    parser.add_argument(
        "--all-pairs",
        action="store_true",
        help="summarise every pair each method scored (default: the pairs all methods scored)",
    )
    parser.add_argument("--reverse", action="store_true", help="work through the pairs backwards")
    parser.add_argument(
        "--save-maps",
        action="store_true",
        help="also save medseg's maps (each solve's) to <out>/maps/<set>_<A>_<B>.npz",
    )
    args = parser.parse_args(argv)
    if args.summarise:
        summarise(args)
    else:
        run(args)
        summarise(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
