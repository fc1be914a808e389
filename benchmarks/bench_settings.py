"""Less work at segment time, and what it costs: settings compared pairwise on held-out cases.

Usage::

    python benchmarks/bench_settings.py --model MODEL --out settings.json [--data DIR]
        [--test-subjects 40] [--seed 0] [--jobs 2] [--shard 0 --n-shards 1]
        [--setting NAME:param=value,param=value ...] [--train-param KEY=VALUE ...]
    python benchmarks/bench_settings.py --phantom-folds 5 --out phantom.json
    python benchmarks/bench_settings.py --summary settings_0.json settings_1.json

The hippocampus subjects (``subjects.csv``) are permuted with ``--seed``; every case of the
first ``--test-subjects`` is held out and the model (labels 1+2, defaults, seeded) is trained
on the cases of the others, or ``--model`` is loaded when it holds one (else the trained model
is saved there). Each held-out case is then segmented once per setting, on one thread, with
the model's segment-time parameters changed (``n_candidates``, ``n_hypotheses``, ``max_iter``,
``refine_levels``, ...): Dice of the union of the labels and seconds, paired with the first
setting. ``--shard`` / ``--n-shards`` split the cases over processes (the seconds of
processes run side by side are comparable with each other, not with a lone run).
``--train-param`` changes the trained model itself (``n_estimators=10``: give it its own
``--model`` folder and its settings their own names); ``--summary`` pairs every setting of
its files with the first on the cases both have, so shards, and runs of two models on the
same cases, make one table.
``--phantom-folds K`` runs the same comparison on the README's phantom protocol instead
(``make_phantom_cohort(20, random_state=seed)``, label 1, K folds by subject with the
evaluation's fold seeds, a model trained per fold), and also records the mean landmark error
(mm). Nothing is written into the repository.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np

from medseg.datasets import load_cohort
from medseg.evaluation.metrics import dice
from medseg.io import select_labels

sys.path.insert(0, str(Path(__file__).parent))
from bench_pose_study import LABELS, _default_data, _param, trained_model  # noqa: E402

PHANTOM_LABELS = (1,)
DEFAULT_SETTINGS = (
    "L15_H4:n_candidates=15,n_hypotheses=4",
    "L20_H4:n_candidates=20,n_hypotheses=4",
    "L12_H4:n_candidates=12,n_hypotheses=4",
    "L15_H2:n_candidates=15,n_hypotheses=2",
)


def _held_out(cohort, n_subjects: int, seed: int) -> tuple[list[int], list[int]]:
    """Training and test cases: every case of ``n_subjects`` permuted subjects is tested."""
    subjects = np.asarray(cohort.subjects)
    held = set(np.random.default_rng(seed).permutation(np.unique(subjects))[:n_subjects])
    test = [i for i, s in enumerate(subjects) if s in held]
    return [i for i, s in enumerate(subjects) if s not in held], test


def _setting(text: str) -> tuple[str, dict]:
    """``NAME:param=value,...`` (values read as JSON) of one setting."""
    name, _, rest = text.partition(":")
    params = {}
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        params[key] = json.loads(value)
    return name, params


def _summary(paths: list[Path]) -> None:
    """One table of every setting in ``paths``, each paired with the first on the cases both
    have: shards of one run (other cases) and runs of another model (other settings, the
    same cases) combine alike. Files without case ids pair within a file only."""
    rows: dict = {}  # setting -> case -> {"dice": ..., "seconds": ..., "error": ...}
    for k, path in enumerate(paths):
        for name, run in json.loads(path.read_text()).items():
            cases = run.get("case") or [f"{k}:{j}" for j in range(len(run["dice"]))]
            got = rows.setdefault(name, {})
            for j, case in enumerate(cases):
                got[case] = {key: run[key][j] for key in run if key != "case" and run[key]}
    first = next(iter(rows))
    print(f"paired with {first}")
    print("| setting | cases | Dice mean | median | min | paired diff ± s.e. | better / worse "
          "| s median | time ratio | landmark error, mm |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, by_case in rows.items():
        both = [c for c in by_case if c in rows[first]]
        if not both:
            print(f"| {name} | 0 | (no case in common with {first}) |")
            continue
        d, t = (np.array([by_case[c][key] for c in both]) for key in ("dice", "seconds"))
        d0, t0 = (np.array([rows[first][c][key] for c in both]) for key in ("dice", "seconds"))
        diff = d - d0
        se = diff.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else float("nan")
        errors = [by_case[c]["error"] for c in both if "error" in by_case[c]]
        print(
            f"| {name} | {len(d)} | {d.mean():.4f} | {np.median(d):.4f} | {d.min():.3f} | "
            f"{diff.mean():+.4f} ± {se:.4f} | {(diff > 0).sum()} / {(diff < 0).sum()} | "
            f"{np.median(t):.2f} | {np.median(t / t0):.2f} | "
            + (f"{np.mean(errors):.2f} |" if errors else "— |")
        )


def _score(model, settings, cohort, cases, labels, out, *, error: bool = False) -> None:
    """Segment ``cases`` with every setting of ``model`` on one thread; append to ``out``
    (with ``error`` also the mean distance of the landmarks to the case's own, mm)."""
    model.n_jobs = 1
    model.detector_.n_jobs = 1
    models = {name: copy.copy(model).set_params(**p) for name, p in settings.items()}
    model.segment(cohort[cases[0]].load_image())  # warm-up, not counted
    for i in cases:
        case = cohort[i]
        image = case.load_image()
        reference = select_labels(case.load_label(), labels)
        truth = case.load_landmarks() if error else None
        for name, m in models.items():
            t0 = time.perf_counter()
            seg = m.segment(image)
            out[name]["seconds"].append(time.perf_counter() - t0)
            out[name]["case"].append(case.case_id)
            out[name]["dice"].append(dice(seg.label, reference))
            if truth is not None:
                error = np.linalg.norm(seg.landmarks - truth, axis=1).mean()
                out[name]["error"].append(float(error))
        print(case.case_id, {k: round(v["dice"][-1], 3) for k, v in out.items()}, flush=True)


def _phantom(settings, n_folds: int, seed: int, jobs: int, fit_params: dict) -> dict:
    """The settings on the phantom, ``n_folds`` folds by subject, a model per fold."""
    from medseg.datasets import make_phantom_cohort
    from medseg.evaluation.folds import fold_seed, make_folds
    from medseg.segmenter import ShapePriorSegmenter

    cohort = make_phantom_cohort(20, random_state=seed)
    out = {name: {"case": [], "dice": [], "error": [], "seconds": []} for name in settings}
    for fold, (train, test) in enumerate(make_folds(cohort, n_folds)):
        model = ShapePriorSegmenter(random_state=fold_seed(seed, fold), n_jobs=jobs, **fit_params)
        model.fit(cohort[train])
        _score(model, settings, cohort, [int(i) for i in test], PHANTOM_LABELS, out, error=True)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=_default_data())
    parser.add_argument("--model", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=None, help="JSON of this shard's figures.")
    parser.add_argument("--test-subjects", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=2, help="Training jobs.")
    parser.add_argument("--shard", type=int, default=0)
    parser.add_argument("--n-shards", type=int, default=1)
    parser.add_argument("--setting", action="append", default=None, help="NAME:param=value,...")
    parser.add_argument(
        "--train-param",
        action="append",
        default=[],
        help="KEY=VALUE (JSON) of the trained model(s), e.g. n_estimators=10.",
    )
    parser.add_argument("--phantom-folds", type=int, default=0, help="Phantom K-fold instead.")
    parser.add_argument("--summary", type=Path, nargs="+", default=None)
    args = parser.parse_args(argv)
    if args.summary:
        _summary(args.summary)
        return 0
    if args.out is None:
        parser.error("--out is required unless --summary")

    settings = dict(_setting(s) for s in (args.setting or DEFAULT_SETTINGS))
    fit_params = dict(_param(text) for text in args.train_param)  # as bench_pose_study --param
    if args.phantom_folds:
        out = _phantom(settings, args.phantom_folds, args.seed, args.jobs, fit_params)
        args.out.write_text(json.dumps(out))
        _summary([args.out])
        return 0
    cohort = load_cohort(args.data)
    train, test = _held_out(cohort, args.test_subjects, args.seed)
    model = trained_model(cohort, train, args.model, seed=args.seed, jobs=args.jobs, **fit_params)
    out = {name: {"case": [], "dice": [], "seconds": []} for name in settings}
    _score(model, settings, cohort, test[args.shard :: args.n_shards], LABELS, out)
    args.out.write_text(json.dumps(out))
    _summary([args.out])
    return 0


if __name__ == "__main__":
    sys.exit(main())
