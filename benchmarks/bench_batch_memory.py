"""Memory of batch inference: does ``medseg-segment`` on a folder stay flat over 100 images?

Trains a small phantom model, writes ``--n-images`` phantom images into a folder, and runs
batch inference over the folder exactly as ``medseg-segment -m MODEL -i FOLDER -o OUT
--jobs 1`` does (``medseg.inference.cli.main`` in one process; the default runs one worker
process per core), measuring the resident set size (VmRSS from ``/proc/<pid>/status``):

* ``subprocess`` (default): a fresh Python process runs the CLI; this script samples its
  VmRSS every ``--interval`` seconds and counts the label maps written so far, so each sample
  is tied to the number of images done;
* ``inprocess``: the CLI runs in this process (what a notebook or a script calling
  ``main([...])`` sees) while a thread samples this process's VmRSS.

Reported: RSS at start (model loaded, the first image done: median while the second runs),
peak, end (median while the last image runs; the exit is left out), and the trend as a
least-squares slope in MiB per image over the images after the first ``--warmup``
(allocator pools and caches fill during the first images). A leak of
even 0.1 MiB per image shows as a slope of 0.1 over 100 images; a flat run has |slope| of a
few hundredths. Wall and CPU time are reported too (the machine is shared).

``--threads 1`` limits the OpenMP / BLAS pools (subprocess: ``OMP_NUM_THREADS`` and friends;
in-process: threadpoolctl). With OpenBLAS's default pool (one thread per core) the RSS
creeps up by about 25 MiB over the first hundred 64^3 images, ever more slowly, as the pool
threads' work buffers get touched (measured 2026-11-23: limiting only the BLAS pool to one
thread makes it flat, while ``MALLOC_ARENA_MAX=1`` does not); with one thread it is flat
from the second image on. Compare both before calling a rise a leak.

Usage::

    python benchmarks/bench_batch_memory.py --out /tmp/batch_memory
    python benchmarks/bench_batch_memory.py --mode inprocess --n-images 100
    python benchmarks/bench_batch_memory.py --mode both --threads 1

Linux only (reads ``/proc``). Generated files go to ``--out`` (default: a temporary folder),
never into the repository.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
_CLI = "import sys; from medseg.inference.cli import main; sys.exit(main(sys.argv[1:]))"
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _rss_mib(pid: int | str = "self") -> float | None:
    """VmRSS of a process in MiB (None once it has exited)."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def _n_done(folder: Path) -> int:
    try:
        return sum(1 for p in folder.iterdir() if p.name.endswith(".nii.gz"))
    except FileNotFoundError:
        return 0


def prepare(out: Path, n_images: int, size: int, seed: int) -> tuple[Path, Path]:
    """A small phantom model and a folder of ``n_images`` phantom images."""
    from medseg.datasets import make_phantom_cohort
    from medseg.io import write_image
    from medseg.segmenter import ShapePriorSegmenter

    model_dir, images = out / "model", out / "images"
    if not model_dir.is_dir():
        t0 = time.perf_counter()
        train = make_phantom_cohort(8, n_landmarks=16, size=size, random_state=seed)
        model = ShapePriorSegmenter(
            n_estimators=20, n_candidates=12, max_iter=100, random_state=seed
        ).fit(train)
        model.save(model_dir)
        print(f"trained and saved the model in {time.perf_counter() - t0:.1f} s")
    images.mkdir(parents=True, exist_ok=True)
    have = _n_done(images)
    if have < n_images:
        t0 = time.perf_counter()
        for start in range(have, n_images, 10):  # batches of 10: bounded memory here too
            count = min(10, n_images - start)
            cohort = make_phantom_cohort(
                count, n_landmarks=16, size=size, random_state=seed + 1000 + start
            )
            for j, case in enumerate(cohort):
                write_image(case.load_image(), images / f"case_{start + j:03d}_0000.nii.gz")
        print(f"wrote {n_images - have} images in {time.perf_counter() - t0:.1f} s")
    return model_dir, images


def _summary(samples: np.ndarray, n_images: int, warmup: int, label: str) -> dict:
    """samples: (S, 3) array of (seconds, images done, RSS MiB)."""
    t, done, rss = samples.T
    # per image count k < n: the median RSS while image k + 1 runs (k done); the samples
    # with all n done are the exit (teardown), left out
    counts = np.array([k for k in range(1, n_images) if (done == k).any()])
    per_image = np.array([np.median(rss[done == k]) for k in counts])
    keep = counts > warmup
    slope = float(np.polyfit(counts[keep], per_image[keep], 1)[0]) if keep.sum() > 2 else np.nan
    end = per_image[-1] if len(per_image) else rss[-1]
    result = {
        "first_sample_mib": float(rss[0]),
        "start_mib": float(per_image[0]),
        "peak_mib": float(rss.max()),
        "end_mib": float(end),
        "slope_mib_per_image": slope,
        "after_warmup_min_max": (float(per_image[keep].min()), float(per_image[keep].max())),
    }
    print(
        f"{label}: RSS start (model loaded, image 2 running) {result['start_mib']:.1f} MiB, "
        f"peak {result['peak_mib']:.1f} MiB, "
        f"end (image {n_images} running) {result['end_mib']:.1f} MiB; "
        f"slope over images {warmup + 1}..{n_images}: "
        f"{slope:+.3f} MiB/image (RSS range after warm-up "
        f"{result['after_warmup_min_max'][0]:.1f}..{result['after_warmup_min_max'][1]:.1f} MiB)"
    )
    deciles = [per_image[min(len(per_image) - 1, k)] for k in range(0, len(per_image), 10)]
    print(f"{label}: RSS with 1, 11, 21, ... done: " + ", ".join(f"{v:.0f}" for v in deciles))
    return result


def run_subprocess(
    model: Path, images: Path, labels: Path, n_images: int, interval: float, threads=None
):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    if threads is not None:
        for name in _THREAD_VARS:
            env[name] = str(threads)
    cmd = [sys.executable, "-c", _CLI, "-m", str(model), "-i", str(images), "-o", str(labels)]
    cmd += ["-q", "--jobs", "1"]  # one process to sample (the default is one per core)
    t0 = time.perf_counter()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.Popen(cmd, env=env, cwd=str(REPO))
    samples = []
    peak_hwm = None
    while proc.poll() is None:
        rss = _rss_mib(proc.pid)
        if rss is not None:
            samples.append((time.perf_counter() - t0, _n_done(labels), rss))
            try:
                with open(f"/proc/{proc.pid}/status", encoding="ascii") as fh:
                    for line in fh:
                        if line.startswith("VmHWM:"):
                            peak_hwm = int(line.split()[1]) / 1024.0
            except FileNotFoundError:
                pass
        time.sleep(interval)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if proc.returncode != 0:
        raise SystemExit(f"medseg-segment exited with {proc.returncode}")
    print(
        f"subprocess: {n_images} images in {wall:.1f} s wall, {cpu:.1f} s CPU "
        f"({wall / n_images:.2f} s/image); VmHWM {peak_hwm:.1f} MiB; "
        f"{len(samples)} samples; load average {os.getloadavg()[0]:.1f}"
    )
    return np.asarray(samples)


def run_inprocess(
    model: Path, images: Path, labels: Path, n_images: int, interval: float, threads=None
):
    from threadpoolctl import threadpool_limits

    from medseg.inference.cli import main

    samples, stop = [], threading.Event()
    t0 = time.perf_counter()

    def sample():
        while not stop.is_set():
            samples.append((time.perf_counter() - t0, _n_done(labels), _rss_mib()))
            stop.wait(interval)

    thread = threading.Thread(target=sample, daemon=True)
    cpu0 = time.process_time()
    thread.start()
    with threadpool_limits(limits=threads):
        code = main(["-m", str(model), "-i", str(images), "-o", str(labels), "-q", "--jobs", "1"])
    samples.append((time.perf_counter() - t0, _n_done(labels), _rss_mib()))
    stop.set()
    thread.join()
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    if code != 0:
        raise SystemExit(f"medseg.inference.cli.main returned {code}")
    print(
        f"inprocess: {n_images} images in {wall:.1f} s wall, {cpu:.1f} s CPU "
        f"({wall / n_images:.2f} s/image); load average {os.getloadavg()[0]:.1f}"
    )
    return np.asarray(samples)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=None, help="Work folder. Default: a temporary one.")
    parser.add_argument("--n-images", type=int, default=100, help="Images. Default: 100.")
    parser.add_argument("--size", type=int, default=64, help="Phantom size. Default: 64.")
    parser.add_argument(
        "--mode", choices=("subprocess", "inprocess", "both"), default="subprocess",
        help="Where the CLI runs. Default: subprocess.",
    )  # fmt: skip
    parser.add_argument("--interval", type=float, default=0.1, help="Sampling period, s.")
    parser.add_argument("--warmup", type=int, default=10, help="Images left out of the slope.")
    parser.add_argument("--seed", type=int, default=0, help="Random seed. Default: 0.")
    parser.add_argument(
        "--threads", type=int, default=None,
        help="Limit the OpenMP / BLAS thread pools. Default: as the environment says.",
    )  # fmt: skip
    args = parser.parse_args(argv)
    out = Path(args.out or tempfile.mkdtemp(prefix="medseg-batch-memory-"))
    model, images = prepare(out, args.n_images, args.size, args.seed)
    modes = ("subprocess", "inprocess") if args.mode == "both" else (args.mode,)
    for mode in modes:
        labels = out / f"labels-{mode}"
        if labels.exists():
            for p in labels.iterdir():
                p.unlink()
        run = run_subprocess if mode == "subprocess" else run_inprocess
        samples = run(model, images, labels, args.n_images, args.interval, args.threads)
        _summary(
            samples, args.n_images, args.warmup, f"{mode}, threads={args.threads or 'default'}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
