"""What a user waits for: training, loading, one case, a folder, against multi-atlas registration.

Usage::

    python benchmarks/bench_speed.py --out speed.json [--data DIR] [--model MODEL]
        [--cases 10] [--folder 61] [--jobs 2] [--atlases 9]

On the hippocampus cohort of ``../shared/data`` (labels 1+2), in one run:

* **training**: ``medseg-train`` on every case with ``--jobs`` (wall seconds, peak memory of
  the process), unless ``--model`` names an existing model folder (reused as it is; a
  ``--model`` that does not exist yet is where the trained model is kept);
* **model**: the folder's size on disk, and in a fresh interpreter (3 times) the seconds of
  importing the segmenter (scikit-learn, SciPy, SimpleITK, ...) and of ``load_model``;
* **one case**: ``segment`` of ``--cases`` images of distinct subjects in this process, on
  one thread and on ``--jobs`` threads (``n_jobs``; the two alternated image by image, the
  first image a warm-up not counted): median seconds and the median of each stage;
* **a folder**: ``medseg-segment --jobs`` on a folder of ``--folder`` images (links to the
  cohort's files): wall seconds and the peak memory of its largest process;
* **the baseline**: :class:`~medseg.evaluation.baselines.MultiAtlasBaseline` (``--atlases``
  atlases, affine, Mattes MI, majority vote; its defaults) fitted on the cases of the other
  subjects and run on the same ``--cases`` images with ``--jobs`` threads: median seconds,
  and the ratios ``baseline / medseg`` per case (one thread against ``--jobs``; and both on
  ``--jobs`` threads) and per case of a folder (both on ``--jobs`` cores).

The figures go to stdout and ``--out`` as JSON. Timings are wall-clock on whatever else the
machine runs: run it alone. Nothing is written into the repository.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

LABELS = "1,2"


def _default_data() -> Path:
    return Path(__file__).resolve().parents[2] / "shared" / "data" / "hippocampus"


def _folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


_MEASURED = (
    "import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True); "
    "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)"
)


def _run_measured(cmd: list[str]) -> tuple[float, float]:
    """Wall seconds of ``cmd`` and the peak resident memory (MiB) of its largest process.

    Run from a fresh interpreter of its own, so that the peak is this command's alone
    (``RUSAGE_CHILDREN`` keeps the largest of every child ever waited for).
    """
    t0 = time.perf_counter()
    run = subprocess.run(
        [sys.executable, "-c", _MEASURED, *cmd], check=True, stdout=subprocess.PIPE, text=True
    )
    wall = time.perf_counter() - t0
    return wall, int(run.stdout.strip().splitlines()[-1]) / 1024.0  # Linux: KiB


def _train(data: Path, model: Path, jobs: int) -> dict:
    cmd = ["medseg-train", str(data), "-o", str(model), "--label", LABELS, "--jobs", str(jobs)]
    wall, peak = _run_measured(cmd + ["-q"])
    return {"seconds": wall, "peak_mb": peak}


def _load_seconds(model: Path, repeat: int = 3) -> dict:
    code = (
        "import sys, time; t = time.perf_counter(); from medseg.segmenter import load_model; "
        "t1 = time.perf_counter(); load_model(sys.argv[1]); "
        "print(t1 - t, time.perf_counter() - t1)"
    )
    imports, loads = [], []
    for _ in range(repeat):
        run = subprocess.run(
            [sys.executable, "-c", code, str(model)], check=True, capture_output=True, text=True
        )
        a, b = run.stdout.strip().splitlines()[-1].split()
        imports.append(float(a))
        loads.append(float(b))
    return {"import_seconds": imports, "load_model_seconds": loads}


def _distinct_subjects(cohort, n: int) -> list[int]:
    seen, picked = set(), []
    for i, subject in enumerate(cohort.subjects):
        if subject not in seen:
            seen.add(subject)
            picked.append(i)
    return picked[:n]


def _per_case(model_dir: Path, cohort, cases: list[int], jobs: int) -> dict:
    from medseg import load_model

    model = load_model(model_dir)
    images = [cohort[i].load_image() for i in cases]
    runs = {threads: ([], {}) for threads in (1, jobs)}  # one entry when jobs is 1
    for threads in runs:  # warm-up: first-call costs (imports, caches, the thread pool)
        model.n_jobs = threads
        model.segment(images[0])
    for image in images[1:]:
        for threads, (seconds, stages) in runs.items():  # alternated: the same drift
            model.n_jobs = threads  # the forests' threads (segment passes it on)
            t0 = time.perf_counter()
            seg = model.segment(image)
            seconds.append(time.perf_counter() - t0)
            for name, value in seg.timings.items():
                stages.setdefault(name, []).append(value)

    def summary(seconds, stages):
        return {
            "median_seconds": float(np.median(seconds)),
            "seconds": seconds,
            "stage_median_seconds": {k: float(np.median(v)) for k, v in stages.items()},
        }

    return summary(*runs[1]) | {
        "threads": {str(t): summary(*run) for t, run in runs.items() if t != 1},
        "peak_mb_this_process": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def _folder(model_dir: Path, cohort, n: int, jobs: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        inputs, outputs = Path(tmp, "in"), Path(tmp, "out")
        inputs.mkdir()
        for case in cohort.cases[:n]:
            os.symlink(case.image, inputs / Path(case.image).name)
        cmd = ["medseg-segment", "-m", str(model_dir), "-i", str(inputs), "-o", str(outputs)]
        wall, peak = _run_measured(cmd + ["--jobs", str(jobs), "-q"])
        written = len(list(outputs.iterdir()))
    return {
        "n_cases": n,
        "jobs": jobs,
        "wall_seconds": wall,
        "seconds_per_case": wall / n,
        "written": written,
        "peak_mb_largest_process": peak,
    }


def _baseline(cohort, cases: list[int], n_atlases: int, jobs: int) -> dict:
    from medseg.evaluation.baselines import MultiAtlasBaseline

    tested = {cohort.subjects[i] for i in cases}
    train = [i for i in range(len(cohort)) if cohort.subjects[i] not in tested]
    baseline = MultiAtlasBaseline(
        labels=(1, 2), n_atlases=n_atlases, random_state=0, n_jobs=jobs
    ).fit(cohort[train])
    seconds = []
    for i in cases:
        image = cohort[i].load_image()
        t0 = time.perf_counter()
        baseline.segment(image)
        seconds.append(time.perf_counter() - t0)
    return {"median_seconds": float(np.median(seconds)), "seconds": seconds, "jobs": jobs}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=_default_data())
    parser.add_argument("--model", type=Path, default=None, help="Reuse this model folder.")
    parser.add_argument("--cases", type=int, default=10)
    parser.add_argument("--folder", type=int, default=61)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--atlases", type=int, default=9)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)

    from medseg.datasets import load_cohort

    cohort = load_cohort(args.data)
    result: dict = {"cohort": str(args.data), "n_cases": len(cohort), "cpu_count": os.cpu_count()}
    with tempfile.TemporaryDirectory() as tmp:
        model = args.model
        if model is None or not model.exists():
            model = model or Path(tmp, "model")
            result["training"] = _train(args.data, model, args.jobs)
            print(json.dumps({"training": result["training"]}), flush=True)
        result["model_mb"] = _folder_bytes(model) / 2**20
        result["load"] = _load_seconds(model)
        print(json.dumps({k: result[k] for k in ("model_mb", "load")}), flush=True)
        cases = _distinct_subjects(cohort, args.cases + 1)
        result["per_case"] = _per_case(model, cohort, cases, args.jobs)
        print(json.dumps({"per_case": result["per_case"]}), flush=True)
        result["folder"] = _folder(model, cohort, min(args.folder, len(cohort)), args.jobs)
        print(json.dumps({"folder": result["folder"]}), flush=True)
    result["multi_atlas"] = _baseline(cohort, cases[1:], args.atlases, args.jobs)
    one = result["per_case"]["median_seconds"]
    atlas = result["multi_atlas"]["median_seconds"]
    result["ratio_baseline_to_medseg_per_case"] = atlas / one
    result["ratio_baseline_to_medseg_folder"] = atlas / result["folder"]["seconds_per_case"]
    threaded = result["per_case"]["threads"].get(str(args.jobs))
    if threaded is not None:  # both on --jobs threads
        result["ratio_baseline_to_medseg_per_case_same_threads"] = (
            atlas / threaded["median_seconds"]
        )
    text = json.dumps(result, indent=1)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
