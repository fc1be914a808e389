"""``medseg-segment``: segment images with a trained model, NIfTI in, NIfTI out.

A folder is segmented in ``--jobs`` worker processes (default: the machine's cores), each
loading the model once, as nnU-Net's predictor does; their number is capped so that they
fit in the memory limit together (:func:`_worker_count`). Only the standard library and
the CLI plumbing are imported here at the top: the segmenter (scikit-learn, SimpleITK,
pyvista, ...: seconds) is imported by the functions that do the work, so that ``--help``
and argument errors answer at once (``tests/test_cli.py`` checks).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from medseg._cli import (
    EXIT_FAILURE,
    EXIT_OK,
    command_parser,
    machine_cores,
    naming,
    positive_int,
    run_cli,
)
from medseg.errors import InputFileError, MedsegError, ResourceLimitError
from medseg.progress import show_progress

if TYPE_CHECKING:
    from concurrent.futures import ProcessPoolExecutor

    from medseg.segmenter import ShapePriorSegmenter

LANDMARK_FORMATS = {"mrk.json": ".mrk.json", "fcsv": ".fcsv", "csv": ".csv"}
SURFACE_FORMATS = ("vtk", "vtp", "stl", "ply")
#: How the worker processes start. Not "fork": the parent has the forests' and BLAS's
#: threads. "forkserver" starts one clean server and forks the workers from it; "spawn"
#: (where there is no forkserver) starts each from scratch.
START_METHOD = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"


def build_parser() -> argparse.ArgumentParser:
    parser = command_parser(
        "medseg-segment",
        "Segment an image, or every image of a folder, with a model from medseg-train. "
        "The label map is written in the input's exact geometry (size, spacing, origin, "
        "direction). nnU-Net style names are understood: case_0000.nii.gz -> case.nii.gz.",
    )
    parser.add_argument("-m", "--model", required=True, help="Model folder from medseg-train.")
    parser.add_argument("-i", "--input", required=True, help="Image file or folder of images.")
    parser.add_argument(
        "-o",
        "--output",
        required=True,
        help="Output file (for one input file) or folder (created if needed).",
    )
    parser.add_argument(
        "--format",
        default=None,
        help="Image format of the label maps, e.g. .nii.gz or .nrrd. Default: the input's.",
    )
    parser.add_argument(
        "--save-landmarks",
        choices=sorted(LANDMARK_FORMATS),
        default=None,
        help="Also write the landmarks (mrk.json for 3D Slicer, fcsv, csv). Default: off.",
    )
    parser.add_argument(
        "--save-surface",
        choices=SURFACE_FORMATS,
        default=None,
        help="Also write the surface mesh in mm. Default: off.",
    )
    parser.add_argument(
        "--no-prior",
        action="store_true",
        help="Detection only: each landmark at its best candidate (a baseline). Default: off.",
    )
    parser.add_argument(
        "--no-boundary",
        action="store_true",
        help="Skip the regional stage: the template warped onto the landmarks, as the model "
        "gives it before the voxel classifier and the graph cut. Default: off.",
    )
    parser.add_argument(
        "--no-appearance-check",
        action="store_true",
        help="Keep the MRF's shape even where the image around it, in the shape's frame, "
        "looks unlike the training images (the check then searches every rotation for the "
        "shape turned about itself, and costs 1-6 s on such a case). Default: the model's "
        "own appearance_check (on for models trained from 2026-12-07 on).",
    )
    parser.add_argument(
        "--jobs",
        type=positive_int,
        default=machine_cores(),
        help="Worker processes segmenting the images of a folder; each loads the model once "
        "and runs its forests on (cores / JOBS) threads. Fewer when JOBS times one image's "
        "estimated peak memory would exceed the memory limit (MEDSEG_MEMORY_LIMIT_GB, "
        "default half the RAM). 1: in this process, its forests on every core; so is one "
        "input file. "
        f"Default: the machine's cores ({machine_cores()} here).",
    )
    return parser


def _inputs(path: Path) -> list[Path]:
    from medseg.io import IMAGE_SUFFIXES, image_suffix

    if path.is_file():
        return [path]
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.is_file() and image_suffix(p))
        if not files:
            raise InputFileError(
                f"{path} holds no image files ({', '.join(IMAGE_SUFFIXES)}); nothing to segment"
            )
        return files
    raise InputFileError(f"{path} does not exist")


def _case_name(path: Path) -> str:
    from medseg.io import image_suffix

    stem = path.name[: -len(image_suffix(path))]
    return stem[:-5] if stem.endswith("_0000") else stem


def _outputs(source: Path, output: Path, batch: bool, fmt: str | None) -> Path:
    from medseg.io import image_suffix

    suffix = fmt or image_suffix(source)
    if not suffix.startswith("."):
        suffix = "." + suffix
    if batch:
        return output / f"{_case_name(source)}{suffix}"
    return output


def _segment_one(
    model: ShapePriorSegmenter, source: Path, target: Path, args: argparse.Namespace
) -> str:
    from medseg.io import atomic_write, image_suffix, write_image, write_landmarks
    from medseg.segmenter import QUALITY_THRESHOLD

    model.boundary = not args.no_boundary
    if args.no_appearance_check:
        model.appearance_check = False
    seg = model.segment(source, use_prior=not args.no_prior)
    write_image(seg.label, target, protect=[source])
    stem = target.name[: -len(image_suffix(target) or target.suffix)]
    if args.save_landmarks:
        write_landmarks(
            seg.landmarks,
            target.with_name(stem + LANDMARK_FORMATS[args.save_landmarks]),
            protect=[source],
        )
    if args.save_surface:
        surface_path = target.with_name(f"{stem}.{args.save_surface}")
        with atomic_write(surface_path, protect=[source]) as tmp:
            seg.surface.save(str(tmp))
    gap = f", duality gap {seg.mrf.gap:.2e}" if seg.mrf is not None else ""
    line = f"{source.name} -> {target}{gap}"
    if seg.appearance is not None and seg.appearance["replaced"]:
        line += f", shape turned by {seg.appearance['turn_deg']:.0f} degrees (appearance check)"
    if seg.quality is not None:
        record = dict(seg.quality, appearance=seg.appearance)
        with atomic_write(target.with_name(f"{stem}.quality.json"), protect=[source]) as tmp:
            tmp.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
        if seg.quality["score"] is not None:
            line += f", quality score {seg.quality['score']:.1f}"
        if seg.quality["flagged"]:
            line += (
                f"\nmedseg-segment: warning: {source.name}: the image disagrees with the shape "
                f"(quality score {seg.quality['score']:.1f} > {QUALITY_THRESHOLD:g}); the "
                "segmentation is likely wrong, check it"
            )
    return line


def _report(text: str, quiet: bool) -> None:
    """A case's line on stdout (unless quiet), its warning line, if any, on stderr."""
    line, _, warning = text.partition("\n")
    if not quiet:
        print(line)
    if warning:
        print(warning, file=sys.stderr)


def _case(
    model: ShapePriorSegmenter, source: Path, target: Path, args: argparse.Namespace
) -> tuple[bool, str]:
    """One image of a folder: ``(True, the line to print)`` or ``(False, why it failed)``."""
    try:
        return True, _segment_one(model, source, target, args)
    except MedsegError as exc:
        return False, str(exc)


# ----------------------------------------------------------------------------- workers

_WORKER_MODEL: ShapePriorSegmenter | None = None
_WORKER_LIMITS = None  # the worker's threadpoolctl limits, kept alive with it
_WORKER_READY = False  # the initializer is done
_WORKER_ENDING = False  # SIGTERM came: run no further case


def _end_worker(signum, frame) -> None:
    """SIGTERM from the parent (:func:`_stop_workers`)."""
    global _WORKER_ENDING
    _WORKER_ENDING = True
    if not _WORKER_READY:  # still loading: nothing to clean up, and a SystemExit out of
        os._exit(128 + signum)  # the initializer would be logged with its traceback
    # unwinds: an atomic write in progress removes its temporary file; the pool's loop then
    # drains the cases already queued (_worker_case refuses them) and exits normally, its
    # exit handlers releasing what the process holds
    raise SystemExit(128 + signum)


def _start_worker(model_path: str, threads: int) -> None:
    """Process-pool initializer: load the model once, with ``threads`` threads everywhere."""
    global _WORKER_MODEL, _WORKER_LIMITS, _WORKER_READY
    # Ctrl-C reaches the whole process group: the parent alone handles it (_stop_workers)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _end_worker)
    import SimpleITK as sitk
    from threadpoolctl import threadpool_limits

    from medseg.segmenter import load_model

    _WORKER_LIMITS = threadpool_limits(limits=threads)  # BLAS / OpenMP pools
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(threads)  # ITK's filters
    model = load_model(model_path)
    model.n_jobs = threads  # the forests' threads at prediction (segment passes it on)
    _WORKER_MODEL = model
    _WORKER_READY = True


def _worker_case(source: str, target: str, args: argparse.Namespace) -> tuple[bool, str]:
    if _WORKER_ENDING:
        raise SystemExit(128 + signal.SIGTERM)
    return _case(_WORKER_MODEL, Path(source), Path(target), args)


def _worker_count(args: argparse.Namespace, model: ShapePriorSegmenter, inputs: list[Path]):
    """``(workers, note)``: ``--jobs``, capped by the images and by the memory limit.

    One image's peak is estimated for the largest input (its header only) with the
    segmenter's own estimate (:func:`medseg.segmenter.segment_bytes`); the workers are as
    many as fit under the limit of :mod:`medseg.memory` together. The note says why, when
    fewer than ``--jobs`` run.
    """
    from medseg.io import read_image_header
    from medseg.memory import format_bytes, memory_limit_bytes
    from medseg.segmenter import segment_bytes

    workers = min(args.jobs, len(inputs))
    if workers < 2:
        return 1, ""
    peak, largest = 0, None
    for path in inputs:
        try:
            size, spacing = read_image_header(path)
        except MedsegError:
            continue  # the worker reports it, as in a serial run
        need = segment_bytes(model, size, spacing, use_prior=not args.no_prior)
        if need > peak:
            peak, largest = need, size
    limit = memory_limit_bytes(model.memory_limit_gb)
    if peak and workers * peak > limit:
        fit = max(1, limit // peak)
        note = (
            f"--jobs {args.jobs} capped to {fit}: one image needs about {format_bytes(peak)} "
            f"(estimated for the largest, {'x'.join(map(str, largest))} voxels) and the memory "
            f"limit is {format_bytes(limit)} (MEDSEG_MEMORY_LIMIT_GB, default half the RAM)"
        )
        return int(fit), note
    return workers, ""


@contextlib.contextmanager
def _sigint_held(*, ignore: bool) -> Iterator[None]:
    """Hold Ctrl-C back while worker processes are launched.

    Ctrl-C reaches the whole process group, and the parent alone handles it
    (:func:`_stop_workers`), so a process must not be half-launched when it comes. With
    ``ignore``, SIGINT is ignored meanwhile: what is started then inherits it ignored, and a
    Python started so installs no KeyboardInterrupt handler (a worker interrupted in its
    imports prints no traceback). Otherwise it is recorded and raised once the block is done.
    """
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers can only be set from the main thread
        return
    caught: list[int] = []
    previous = signal.signal(
        signal.SIGINT, signal.SIG_IGN if ignore else lambda signum, frame: caught.append(signum)
    )
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        raise KeyboardInterrupt


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Cancel the images not started and end the workers now (interrupt, or a bug)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())  # its own handles
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in processes:
        proc.terminate()  # SIGTERM: _end_worker unwinds, an atomic write cleans up after it
    for proc in processes:
        proc.join(timeout=30)
        if proc.is_alive():
            proc.kill()
    pool.shutdown(wait=True)  # its manager thread releases the queues (no leaked semaphores)


def _in_workers(
    cases: list[tuple[Path, Path]], args: argparse.Namespace, workers: int
) -> Iterator[tuple[int, bool, str]]:
    """``(index, ok, line or reason)`` of each case as the worker processes complete them."""
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    threads = max(1, machine_cores() // workers)
    context = multiprocessing.get_context(START_METHOD)
    if START_METHOD == "forkserver":
        # the server imports the segmenter once and forks the workers with it: each worker
        # importing it anew costs seconds of CPU (measured: 2 workers, 7 phantom images,
        # results after 10-12 s instead of 17-21 s with "spawn" or a bare forkserver)
        context.set_forkserver_preload([__name__, "medseg.segmenter"])
        from multiprocessing import forkserver

        with _sigint_held(ignore=True):  # the workers fork from the server: they inherit it
            forkserver.ensure_running()
    pool = ProcessPoolExecutor(
        workers,
        mp_context=context,
        initializer=_start_worker,
        initargs=(str(args.model), threads),
    )
    try:
        # the first submissions start the workers ("spawn": fresh interpreters, which
        # must inherit SIGINT ignored; "forkserver": forked from the server, which the first
        # one waits for while it imports the segmenter, so Ctrl-C is only held back there)
        with _sigint_held(ignore=START_METHOD == "spawn"):
            futures = {
                pool.submit(_worker_case, str(source), str(target), args): index
                for index, (source, target) in enumerate(cases)
            }
        for future in as_completed(futures):
            try:
                ok, text = future.result()
            except BrokenProcessPool:
                raise ResourceLimitError(
                    "a worker process ended abruptly (killed, perhaps for lack of memory); "
                    "the label maps written so far are complete. Rerun with fewer --jobs, or "
                    "a lower MEDSEG_MEMORY_LIMIT_GB"
                ) from None
            yield futures[future], ok, text
    except BaseException:
        _stop_workers(pool)
        raise
    pool.shutdown()


# ----------------------------------------------------------------------------- the command


def _run(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from medseg.io import IMAGE_SUFFIXES, image_suffix
    from medseg.segmenter import load_model

    model = load_model(args.model)
    model.n_jobs = machine_cores()  # in this process: every core (a worker takes its share)
    if not args.no_boundary and getattr(model, "boundary_", None) is None:
        print(
            f"medseg-segment: {args.model} has no regional stage (trained with --no-boundary, "
            "or saved before model format 5): the label maps are the template warped onto "
            "the landmarks",
            file=sys.stderr,
        )
    source = Path(args.input)
    inputs = _inputs(source)
    batch = source.is_dir()
    output = Path(args.output)
    if batch:
        if output.exists() and not output.is_dir():
            raise InputFileError(f"{output} is a file; with a folder input give a folder")
        output.mkdir(parents=True, exist_ok=True)
    elif image_suffix(output) is None:
        raise InputFileError(
            f"{output}: give an output file name ending in one of {', '.join(IMAGE_SUFFIXES)}"
        )
    cases = [(path, _outputs(path, output, batch, args.format)) for path in inputs]
    if not batch:  # one file: in this process, its error is the command's
        try:
            line = _segment_one(model, *cases[0], args)
        except MedsegError as exc:
            raise naming(exc, cases[0][0]) from None
        _report(line, args.quiet)
        return EXIT_OK

    workers, note = _worker_count(args, model, inputs)
    if workers > 1:
        del model  # each worker loads its own
        if not args.quiet:
            threads = max(1, machine_cores() // workers)
            print(
                f"medseg-segment: {len(cases)} images in {workers} worker processes, "
                f"{threads} forest thread{'s' if threads > 1 else ''} each"
                + (f"; {note}" if note else ""),
                file=sys.stderr,
            )
        done = _in_workers(cases, args, workers)
    else:
        if note and not args.quiet:
            print(f"medseg-segment: {note}", file=sys.stderr)
        done = ((i, *_case(model, src, dst, args)) for i, (src, dst) in enumerate(cases))

    # lines in input order, the progress bar over completed images
    failed, waiting, first = 0, {}, 0
    with tqdm(total=len(cases), desc="segmenting", disable=not show_progress(args.quiet)) as bar:
        for index, ok, text in done:
            bar.update()
            waiting[index] = (ok, text)
            while first in waiting:
                ok, text = waiting.pop(first)
                if not ok:
                    failed += 1
                    print(
                        f"medseg-segment: skipped {cases[first][0].name}: {text}", file=sys.stderr
                    )
                else:
                    _report(text, args.quiet)
                first += 1
    if failed:
        print(f"medseg-segment: {failed} of {len(inputs)} images failed", file=sys.stderr)
        return EXIT_FAILURE
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_run, build_parser(), argv)
