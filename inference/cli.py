"""``medseg-segment``: segment images with a trained model, NIfTI in, NIfTI out."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from tqdm.auto import tqdm

from medseg._cli import EXIT_FAILURE, EXIT_OK, command_parser, naming, run_cli
from medseg.errors import InputFileError, MedsegError
from medseg.io import IMAGE_SUFFIXES, atomic_write, image_suffix, write_image, write_landmarks
from medseg.progress import show_progress
from medseg.segmenter import ShapePriorSegmenter, load_model

LANDMARK_FORMATS = {"mrk.json": ".mrk.json", "fcsv": ".fcsv", "csv": ".csv"}
SURFACE_FORMATS = ("vtk", "vtp", "stl", "ply")


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
    return parser


def _inputs(path: Path) -> list[Path]:
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
    stem = path.name[: -len(image_suffix(path))]
    return stem[:-5] if stem.endswith("_0000") else stem


def _outputs(source: Path, output: Path, batch: bool, fmt: str | None) -> Path:
    suffix = fmt or image_suffix(source)
    if not suffix.startswith("."):
        suffix = "." + suffix
    if batch:
        return output / f"{_case_name(source)}{suffix}"
    return output


def _segment_one(
    model: ShapePriorSegmenter, source: Path, target: Path, args: argparse.Namespace
) -> str:
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
    return f"{source.name} -> {target}{gap}"


def _run(args: argparse.Namespace) -> int:
    model = load_model(args.model)
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

    failed = 0
    for path in tqdm(inputs, desc="segmenting", disable=not show_progress(args.quiet)):
        try:
            line = _segment_one(model, path, _outputs(path, output, batch, args.format), args)
        except MedsegError as exc:
            if not batch:
                raise naming(exc, path) from None
            failed += 1
            print(f"medseg-segment: skipped {path.name}: {exc}", file=sys.stderr)
            continue
        if not args.quiet:
            print(line)
    if failed:
        print(f"medseg-segment: {failed} of {len(inputs)} images failed", file=sys.stderr)
        return EXIT_FAILURE
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(_run, build_parser(), argv)
