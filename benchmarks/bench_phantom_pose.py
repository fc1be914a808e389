"""The phantom's pose curve in expectation: each case under several draws of each angle.

Usage::

    python benchmarks/bench_phantom_pose.py --out draws.jsonl [--models DIR]
        [--angles 1,15,30,45,90] [--draws 6] [--fov] [--shard 0 --n-shards 1] [--seed 0]
    python benchmarks/bench_phantom_pose.py --summary draws.jsonl [more.jsonl ...]

The embedded phantom cohort (``make_phantom_cohort(20, random_state=seed)``), 5 folds by
subject, the segmenter's fold models exactly as ``medseg-evaluate phantom --folds 5`` fits
them (same seeds; kept in ``--models`` and reused when there). Each test case is segmented
as acquired and rotated by each angle about ``--draws`` random axes through the image
centre (``rotN`` of :mod:`medseg.evaluation.perturbation`, on the grid padded by 15 mm).
Draw 0 uses the evaluation's own seed, so it is ``medseg-evaluate``'s row; draw ``d`` the
seed of the condition ``rotN#d``. ``--fov`` adds the field of view alone, without a
rotation: padded by 15 mm of zeros (``pad_zeros``, one draw: nothing in it is random) and of
noise like the image's background (``pad_noise``, ``--draws`` draws of the noise).

Why draws: on the phantom a case's outcome is bimodal (right configuration, Dice about
0.95; wrong one, below 0.6), and a small change of the input (15 mm of zero padding, half
a voxel of shift) flips some cases either way. One draw per angle and 20 cases then gives
a curve whose points differ by 0.05-0.1 from sampling alone. The mean over draws estimates
the expected Dice at each angle; the summary gives it with its standard error (cases as
clusters) and its difference from 1 degree (resampling with hardly any rotation), paired
by case.

One JSON line per (case, angle, draw), with its Dice and, when the model has the appearance
check, whether it searched and replaced; a case the segmenter refuses (``MedsegError``)
scores Dice 0, as in ``medseg-evaluate``. ``--shard`` / ``--n-shards`` split the cases among
processes (their files summarise together). Nothing is written into the repository.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from medseg.datasets import make_phantom_cohort
from medseg.errors import MedsegError
from medseg.evaluation.fold import _perturbation_seed
from medseg.evaluation.folds import fold_seed, make_folds
from medseg.evaluation.methods import default_methods
from medseg.evaluation.metrics import score_segmentation
from medseg.evaluation.perturbation import perturb_condition
from medseg.io import label_values
from medseg.segmenter import ShapePriorSegmenter, load_model

N_SUBJECTS = 20
N_FOLDS = 5
LABELS = (1,)
FOV = ("pad_zeros", "pad_noise")
ONE_DRAW = ("acquired", "pad_zeros")  # nothing random in them


def _fold_model(cohort, train, fold: int, seed: int, models: Path | None):
    """The fold's segmenter as ``medseg-evaluate`` fits it, kept in ``models``."""
    folder = None if models is None else models / f"fold{fold}"
    if folder is not None and (folder / "model.json").is_file():
        return load_model(folder)
    spec = default_methods(["shape_prior"], labels=LABELS)[0]
    model: ShapePriorSegmenter = spec.build(fold_seed(seed, fold))
    model.fit(cohort[train])
    if folder is not None:
        model.save(folder)
    return model


def _condition_seed(seed: int, case_id: str, condition: str, draw: int) -> int:
    name = condition if draw == 0 else f"{condition}#{draw}"
    return _perturbation_seed(seed, case_id, name)


def _scored(model, image, labels, condition: str, seed: int) -> dict:
    """Dice of ``model`` on the case under ``condition`` (0 when it refuses the case, as in
    ``medseg-evaluate``), and whether the appearance check searched and replaced."""
    moved, moved_labels, *_ = perturb_condition(condition, image, labels, random_state=seed)
    try:
        seg = model.segment(moved)
    except MedsegError as exc:
        print(f"{condition} (seed {seed}): {exc}", file=sys.stderr)
        return {"dice": 0.0}
    seen = {k: v for k, v in (seg.appearance or {}).items() if k in ("searched", "replaced")}
    return {"dice": score_segmentation(seg.label, moved_labels).dice, **seen}


def run(args) -> None:
    cohort = make_phantom_cohort(N_SUBJECTS, random_state=args.seed)
    conditions = ["acquired"] + (list(FOV) if args.fov else []) + [f"rot{a:g}" for a in args.angles]
    done = set()
    if args.out.exists():
        for line in args.out.read_text().splitlines():
            row = json.loads(line)
            done.add((row["case"], row["condition"], row["draw"]))
    with args.out.open("a") as fh:
        for fold, (train, test) in enumerate(make_folds(cohort, N_FOLDS)):
            mine = [int(i) for i in test if int(i) % args.n_shards == args.shard]
            if not mine:
                continue
            model = _fold_model(cohort, train, fold, args.seed, args.models)
            model.n_jobs = 1
            for i in mine:
                case = cohort[i]
                image, labels = case.load_image(), label_values(case.load_label(), LABELS)
                for condition in conditions:
                    for draw in range(1 if condition in ONE_DRAW else args.draws):
                        if (case.case_id, condition, draw) in done:
                            continue
                        seed = _condition_seed(args.seed, case.case_id, condition, draw)
                        row = {
                            "fold": fold,
                            "case": case.case_id,
                            "condition": condition,
                            "draw": draw,
                            **_scored(model, image, labels, condition, seed),
                        }
                        fh.write(json.dumps(row) + "\n")
                        fh.flush()


def summary(paths: list[Path]) -> None:
    """Mean Dice per condition (cases as clusters), and its paired difference from the
    1-degree rotation and from the acquired case."""
    dice: dict = defaultdict(lambda: defaultdict(list))  # condition -> case -> [dice]
    for path in paths:
        for line in path.read_text().splitlines():
            row = json.loads(line)
            dice[row["condition"]][row["case"]].append(row["dice"])
    low = next((c for c in dice if c.startswith("rot") and float(c[3:]) < 5), None)
    references = [c for c in (low, "acquired") if c in dice]
    print(
        f"{'condition':<10} {'cases':>5} {'draws':>6} {'mean':>7} {'s.e.':>6}"
        + "".join(f"  {'vs ' + c:>22}" for c in references)
    )
    for condition, cases in sorted(dice.items(), key=lambda kv: _angle(kv[0])):
        per_case = {case: float(np.mean(v)) for case, v in cases.items()}
        values = np.array(list(per_case.values()))
        line = (
            f"{condition:<10} {len(values):>5} {sum(map(len, cases.values())):>6} "
            f"{values.mean():>7.4f} {_se(values):>6.4f}"
        )
        for reference in references:
            both = sorted(set(per_case) & set(dice[reference]))
            diff = np.array([per_case[c] - np.mean(dice[reference][c]) for c in both])
            shown = condition != reference and len(diff) > 1
            line += f"  {diff.mean():+.4f} (s.e. {_se(diff):.4f})" if shown else f"  {'':>22}"
        print(line)


def _se(values: np.ndarray) -> float:
    return values.std(ddof=1) / np.sqrt(len(values)) if len(values) > 1 else float("nan")


def _angle(condition: str) -> float:
    """Sort key: acquired, the padded fields of view, then the angles."""
    order = ("acquired",) + FOV
    return order.index(condition) - len(order) if condition in order else float(condition[3:])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--models", type=Path, default=None)
    parser.add_argument(
        "--angles", type=lambda s: [float(a) for a in s.split(",")], default=[1, 15, 30, 45, 90]
    )
    parser.add_argument("--draws", type=int, default=6)
    parser.add_argument("--fov", action="store_true", help="Also pad_zeros and pad_noise.")
    parser.add_argument("--shard", type=int, default=0)
    parser.add_argument("--n-shards", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--summary", type=Path, nargs="+", default=None)
    args = parser.parse_args(argv)
    if args.summary:
        summary(args.summary)
        return 0
    if args.out is None:
        parser.error("--out is required unless --summary")
    run(args)
    summary([args.out])
    return 0


if __name__ == "__main__":
    sys.exit(main())
