"""The regional stage's cut on a synthetic band: seconds per cut, and how much of it is max-flow.

Usage::

    python benchmarks/bench_cut.py [--shape 60 80 60] [--repeats 5] [--seed 0] [--out cut.json]

A Potts problem of the size the regional stage solves on a hippocampus case (the band of a
bent ellipsoid with two sub-labels on a grid of about 0.7 mm: some 40,000 voxels and
120,000 edges, background and two labels, ``-log p`` of a noisy probability map, contrast
weights of a noisy image) is minimised by :func:`medseg.mrf.potts_expansion`
``--repeats`` times. Reported: the median seconds per cut, its expansion moves, and the
seconds inside SciPy's max-flow and the residual search in the same runs, so that the
figure to compare across versions is the ratio of the rest (building, reducing and
rounding each move's network) to the max-flow, not the seconds of one machine. Nothing
is written into the repository.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from medseg.mrf import _cut
from medseg.mrf._cut import grid_edges, potts_expansion


def band_problem(shape, seed: int):
    """Unaries (n, 3), edges and weights of a noisy two-part ellipsoid's 4-voxel band."""
    rng = np.random.default_rng(seed)
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, s) for s in shape], indexing="ij")
    radius = np.sqrt((z / 0.45) ** 2 + (y / 0.8) ** 2 + (x / 0.45) ** 2)
    inside = radius < 1.0
    truth = np.where(inside, np.where(y < 0.1, 1, 2), 0)
    voxel = 2.0 / max(shape)
    band = np.abs(radius - 1.0) * 0.6 < 4 * voxel
    nodes = band | inside
    logits = np.stack([truth == k for k in range(3)], axis=-1) * 2.0
    logits = logits + rng.normal(scale=1.0, size=logits.shape)
    proba = np.exp(logits) / np.exp(logits).sum(axis=-1, keepdims=True)
    unary = -np.log(np.clip(proba[nodes], 1e-3, None))
    image = truth * 40.0 + rng.normal(scale=10.0, size=shape)
    edges, lengths = grid_edges(nodes, (0.7, 0.7, 0.7))
    values = image[nodes]
    diff2 = (values[edges[:, 0]] - values[edges[:, 1]]) ** 2
    weights = 0.5 * np.exp(-diff2 / (2 * diff2.mean())) / lengths
    return unary, edges, weights


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shape", type=int, nargs=3, default=(60, 80, 60))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    unary, edges, weights = band_problem(tuple(args.shape), args.seed)
    flow = {"seconds": 0.0, "moves": 0}
    min_cut = _cut._min_cut_source_side

    def timed(capacity, source, sink):
        t0 = time.perf_counter()
        try:
            return min_cut(capacity, source, sink)
        finally:
            flow["seconds"] += time.perf_counter() - t0
            flow["moves"] += 1

    _cut._min_cut_source_side = timed
    try:
        potts_expansion(unary, edges, weights)  # warm-up
        cuts, flows, moves = [], [], []
        for _ in range(args.repeats):
            flow.update(seconds=0.0, moves=0)
            t0 = time.perf_counter()
            potts_expansion(unary, edges, weights)
            cuts.append(time.perf_counter() - t0)
            flows.append(flow["seconds"])
            moves.append(flow["moves"])
    finally:
        _cut._min_cut_source_side = min_cut
    cut, in_flow = float(np.median(cuts)), float(np.median(flows))
    result = {
        "nodes": int(unary.shape[0]),
        "edges": int(edges.shape[0]),
        "moves": int(np.median(moves)),
        "seconds_per_cut": cut,
        "seconds_in_max_flow": in_flow,
        "rest_to_max_flow": (cut - in_flow) / in_flow,
    }
    print(json.dumps(result, indent=1))
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
