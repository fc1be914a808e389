"""The evaluation report: tables, JSON summary and figures from the per-case CSV.

(Slightly over 400 lines: the four figures are small functions of one idea, the report.)

:func:`write_report` reads ``cases.csv`` (written by :func:`medseg.evaluation.runner.run_folds`)
and writes, next to it:

* ``summary.md``: per method (unperturbed cases) the number of cases, Dice, HD95, ASSD,
  landmark error in mm and voxels, duality gap and seconds per case (mean +- standard
  deviation, NaN-aware), the landmark-error ratio of every baseline to the method, and the
  pose-perturbation tables: mean Dice per method by rotation angle (the ``rotN``
  conditions, 0 the unperturbed case), by scale (the ``scaleS`` conditions, 1 the
  unperturbed case), and one row per other condition (``random``, ``pad_zeros``, ...) with
  the Dice loss against the unperturbed case;
* ``summary.json``: ``metric_per_case`` (the rows), ``mean`` (per method, per metric) and
  ``foreground_mean`` (nnU-Net's key; one structure is scored, the union of the chosen
  labels, so it holds the same per-method means), plus ``perturbation`` (per method and
  condition name: mean Dice, HD95, landmark errors, angle, scale, Dice loss, count);
  ``dice_by_label`` (per method, the mean Dice of each label of a reference of several)
  and ``flagging`` (per method with a quality score: ROC AUC for telling cases under
  Dice 0.75, :mod:`medseg.evaluation.flagging`); written with ``sort_keys=True``, NaN and
  infinities as ``null``;
* ``landmark_error_boxplot.png``: landmark error by method, as in the paper's Fig. 2(c),
  with a Dice panel;
* ``perturbation.png``: mean Dice against the rotation angle and against the scale, and the
  Dice loss of the other conditions;
* ``overlays.png``: best, median and worst case (by Dice) of the main method, three
  orthogonal slices through the reference structure, reference and prediction contours;
* ``surface.png``: off-screen pyvista rendering of the median case's predicted surface
  (marching cubes of the predicted label map) over the reference surface.

Every file is written atomically.
"""

from __future__ import annotations

import json
import math
import os
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from medseg.errors import InputFileError, MedsegError
from medseg.evaluation.flagging import FAILURE_DICE, flagging_scores
from medseg.evaluation.methods import METHOD_NAMES
from medseg.evaluation.perturbation import CONDITIONS, UNPERTURBED, parse_condition
from medseg.evaluation.results import SCORES, prediction_path, read_results
from medseg.io import atomic_write, read_image, select_labels, voxel_to_physical

__all__ = ["summarise", "write_report", "METRICS"]

#: Metrics summarised per method, in table order.
METRICS = (*SCORES, "seconds")
_HEADERS = {
    "dice": "Dice",
    "hd95": "HD95 (mm)",
    "assd": "ASSD (mm)",
    "landmark_error_mm": "landmark error (mm)",
    "landmark_error_vox": "landmark error (vox)",
    "gap": "duality gap",
    "seconds": "s / case",
}
_PREFERRED = METHOD_NAMES  # the methods in their order, others after them
# Means per condition in summary.json, besides the Dice loss, angle, scale and count.
_PERTURBATION_SCORES = ("dice", "landmark_error_mm", "landmark_error_vox", "hd95")


def _methods(rows: list[dict]) -> list[str]:
    names = sorted({r["method"] for r in rows})
    return [m for m in _PREFERRED if m in names] + [m for m in names if m not in _PREFERRED]


def _nan_stats(values: Sequence[float]) -> dict:
    v = np.asarray(values, dtype=float)
    finite = v[np.isfinite(v)]
    return {
        "mean": float(finite.mean()) if finite.size else math.nan,
        "std": float(finite.std()) if finite.size else math.nan,
        "median": float(np.median(finite)) if finite.size else math.nan,
        "n": int(v.size),
        "n_finite": int(finite.size),
    }


def _unperturbed(rows: list[dict]) -> list[dict]:
    return [r for r in rows if r["perturbation"] == UNPERTURBED]


def summarise(rows: list[dict]) -> dict:
    """Per-method statistics of the unperturbed rows and means per perturbation condition.

    Parameters
    ----------
    rows : list of dict
        Rows of :func:`medseg.evaluation.results.read_results`.

    Returns
    -------
    summary : dict
        ``{"methods": [...], "stats": {method: {metric: {"mean", "std", "median", "n",
        "n_finite"}}}, "perturbation": {method: {condition: {"dice", "hd95",
        "landmark_error_mm", "landmark_error_vox", "angle_deg", "scale", "dice_loss",
        "n"}}}}``. Means skip NaN and infinite values; ``n_finite`` says how many were used.
        ``dice_loss`` is the mean over the cases that have both rows of the unperturbed
        Dice minus the condition's (positive: worse under the perturbation; 0 for
        ``acquired`` itself, NaN without unperturbed rows).
    """
    methods = _methods(rows)
    base = _unperturbed(rows)
    stats = {
        m: {k: _nan_stats([r[k] for r in base if r["method"] == m]) for k in METRICS}
        for m in methods
    }
    reference = {(r["method"], r["fold"], r["case"]): r["dice"] for r in base}
    groups: dict = defaultdict(list)
    for r in rows:
        groups[(r["method"], r["perturbation"])].append(r)
    perturbation: dict = defaultdict(dict)
    for (m, condition), rs in sorted(groups.items()):
        losses = [
            reference[key] - r["dice"]
            for r in rs
            if (key := (m, r["fold"], r["case"])) in reference
        ]
        perturbation[m][condition] = {
            k: _nan_stats([r[k] for r in rs])["mean"]
            for k in (*_PERTURBATION_SCORES, "perturbation_deg", "scale")
        } | {"dice_loss": _nan_stats(losses)["mean"], "n": len(rs)}
        perturbation[m][condition]["angle_deg"] = perturbation[m][condition].pop("perturbation_deg")
    return {
        "methods": methods,
        "stats": stats,
        "perturbation": dict(perturbation),
        "by_label": _by_label(base),
        "flagging": flagging_scores(base),
    }


def _by_label(rows: list[dict]) -> dict:
    """``{method: {label value: mean Dice}}`` from the ``dice_by_label`` column (methods
    whose reference has a single label are left out)."""
    values: dict = defaultdict(lambda: defaultdict(list))
    for r in rows:
        for part in filter(None, str(r.get("dice_by_label", "")).split(";")):
            label, _, dice = part.partition(":")
            values[r["method"]][int(label)].append(float(dice))
    return {
        m: {v: _nan_stats(d)["mean"] for v, d in sorted(per.items())} for m, per in values.items()
    }


def _condition_groups(summary: dict) -> tuple[list, list, list]:
    """The conditions of a summary, by table: ``[(angle, name)]`` of the rotations (0 the
    unperturbed case), ``[(scale, name)]`` of the scalings (1 the unperturbed case), and
    the names of the others (``random``, ``pad_*``, ``rot0``, ``scale1``, unknown names)."""
    names = {c for per in summary["perturbation"].values() for c in per}
    rotations, scales, others = [], [], []
    for name in names - {UNPERTURBED}:
        try:
            condition = parse_condition(name)
        except MedsegError:  # a hand-made results file: shown as it is
            condition = None
        if condition is not None and condition.kind == "rotation" and condition.angle_deg > 0:
            rotations.append((condition.angle_deg, name))
        elif condition is not None and condition.kind == "scale" and condition.scale != 1:
            scales.append((condition.scale, name))
        else:
            others.append(name)
    if UNPERTURBED in names:
        rotations += [(0.0, UNPERTURBED)] if rotations else []
        scales += [(1.0, UNPERTURBED)] if scales else []
    known = {c: i for i, c in enumerate(CONDITIONS)}
    others.sort(key=lambda c: (known.get(c, len(known)), c))
    return sorted(rotations), sorted(scales), others


# ----------------------------------------------------------------------------- tables


def _fmt(x: float, digits: int = 3) -> str:
    return "n/a" if not np.isfinite(x) else f"{x:.{digits}f}"


def _markdown(summary: dict, title: str) -> str:
    methods, stats = summary["methods"], summary["stats"]
    lines = [
        f"# {title}",
        "",
        "Unperturbed test cases (mean ± sd over cases; NaN/inf skipped).",
        "",
    ]
    lines.append("| method | cases | " + " | ".join(_HEADERS[k] for k in METRICS) + " |")
    lines.append("|---|---:|" + "---:|" * len(METRICS))
    for m in methods:
        cells = []
        for k in METRICS:
            s = stats[m][k]
            cell = f"{_fmt(s['mean'])} ± {_fmt(s['std'])}" if s["n_finite"] else "n/a"
            if 0 < s["n_finite"] < s["n"]:
                cell += f" ({s['n_finite']}/{s['n']})"
            cells.append(cell)
        lines.append(f"| {m} | {stats[m]['dice']['n']} | " + " | ".join(cells) + " |")
    lines += ["", "Medians over the same cases:", "", "| method | Dice | HD95 (mm) | ASSD (mm) |"]
    lines.append("|---|---:|---:|---:|")
    for m in methods:
        cells = [_fmt(stats[m][k]["median"]) for k in ("dice", "hd95", "assd")]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    main = methods[0] if methods else None
    if main is not None and len(methods) > 1:
        ref = stats[main]["landmark_error_mm"]["mean"]
        lines += ["", f"Landmark error relative to `{main}` (mean / mean):", ""]
        for m in methods[1:]:
            other = stats[m]["landmark_error_mm"]["mean"]
            ratio = other / ref if ref and np.isfinite(ref) else math.nan
            lines.append(f"- `{m}`: {_fmt(ratio, 2)} x")
    lines += _label_table(summary)
    lines += _flagging_table(summary)
    lines += _perturbation_tables(summary)
    return "\n".join(lines) + "\n"


def _label_table(summary: dict) -> list[str]:
    """Mean Dice of each label of the reference, per method (references of several labels)."""
    by_label = summary.get("by_label") or {}
    values = sorted({v for per in by_label.values() for v in per})
    if not values:
        return []
    lines = ["", "Dice per label (unperturbed, mean over cases):", ""]
    lines.append("| method | " + " | ".join(f"label {v}" for v in values) + " |")
    lines.append("|---|" + "---:|" * len(values))
    for m in summary["methods"]:
        if m in by_label:
            cells = [_fmt(by_label[m].get(v, math.nan)) for v in values]
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return lines


def _flagging_table(summary: dict) -> list[str]:
    """How well each method's own quality score flags its failed cases."""
    flagging = summary.get("flagging") or {}
    methods = [m for m in summary["methods"] if m in flagging]
    if not methods:
        return []
    lines = [
        "",
        f"Quality score against failure (Dice under {FAILURE_DICE:g}; unperturbed):",
        "",
        "| method | cases | failed | ROC AUC | flagged | failed and flagged |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for m in methods:
        f = flagging[m]
        lines.append(
            f"| {m} | {f['n']} | {f['failed']} | {_fmt(f['auc'])} | {f['flagged']} "
            f"| {f['flagged_failed']} |"
        )
    return lines


def _perturbation_tables(summary: dict) -> list[str]:
    methods, per = summary["methods"], summary["perturbation"]
    rotations, scales, others = _condition_groups(summary)
    if not (rotations or scales or others):
        return []
    lines = [
        "",
        "## Pose perturbation",
        "",
        "Each test case under named conditions (`medseg.evaluation.perturbation`): all but "
        "the unperturbed case on its grid padded by 15 mm, the transforms about the image "
        "centre.",
    ]

    def cell(m: str, name: str) -> str:
        return _fmt(per[m][name]["dice"]) if name in per.get(m, {}) else "-"

    for title, columns in (
        ("Mean Dice by rotation angle (rotation only; 0: unperturbed).", rotations),
        ("Mean Dice by scale (scale only; 1: unperturbed).", scales),
    ):
        if not columns:
            continue
        unit = " deg" if columns is rotations else ""
        lines += [
            "",
            title,
            "",
            "| method | " + " | ".join(f"{v:g}{unit}" for v, _ in columns) + " |",
            "|---|" + "---:|" * len(columns),
        ]
        lines += [f"| {m} | " + " | ".join(cell(m, n) for _, n in columns) + " |" for m in methods]
    if others:
        lines += [
            "",
            "Other conditions: mean Dice (loss: unperturbed minus perturbed Dice, paired by "
            "case; positive is worse).",
            "",
            "| condition | " + " | ".join(methods) + " |",
            "|---|" + "---:|" * len(methods),
        ]
        for name in others:
            cells = [
                f"{_fmt(per[m][name]['dice'])} (loss {_fmt(per[m][name]['dice_loss'])})"
                if name in per.get(m, {})
                else "-"
                for m in methods
            ]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, float | np.floating):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def _summary_json(rows: list[dict], summary: dict) -> str:
    means = {m: {k: s["mean"] for k, s in per.items()} for m, per in summary["stats"].items()}
    payload = {
        "metric_per_case": rows,
        "mean": means,
        "foreground_mean": means,
        "perturbation": summary["perturbation"],
        "dice_by_label": summary["by_label"],
        "flagging": summary["flagging"],
    }
    return json.dumps(_jsonable(payload), indent=2, sort_keys=True, allow_nan=False)


# ----------------------------------------------------------------------------- figures


def _figure_path_write(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_write(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)


def _boxplots(rows: list[dict], methods: list[str], path: Path) -> None:
    import matplotlib.pyplot as plt

    base = _unperturbed(rows)
    fig, axes = plt.subplots(1, 2, figsize=(4 + 1.6 * len(methods), 4))
    for ax, key, label in (
        (axes[0], "landmark_error_mm", "landmark error (mm)"),
        (axes[1], "dice", "Dice"),
    ):
        data = [[r[key] for r in base if r["method"] == m and np.isfinite(r[key])] for m in methods]
        ax.boxplot(data, showmeans=True)
        ax.set_xticks(range(1, len(methods) + 1), methods, rotation=20)
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_title("Landmark error by method")
    axes[1].set_title("Dice by method")
    fig.tight_layout()
    _figure_path_write(fig, path)


def _perturbation_plot(summary: dict, methods: list[str], path: Path) -> None:
    import matplotlib.pyplot as plt

    rotations, scales, others = _condition_groups(summary)
    panels = [p for p, items in (("rot", rotations), ("scale", scales), ("other", others)) if items]
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4), squeeze=False)
    for ax, panel in zip(axes[0], panels, strict=True):
        if panel == "other":
            width = 0.8 / len(methods)
            for j, m in enumerate(methods):
                per = summary["perturbation"].get(m, {})
                loss = [per[c]["dice_loss"] if c in per else np.nan for c in others]
                ax.bar(np.arange(len(others)) + (j - (len(methods) - 1) / 2) * width, loss,
                       width, label=m)  # fmt: skip
            ax.set_xticks(range(len(others)), others, rotation=20)
            ax.axhline(0.0, color="k", linewidth=0.8)
            ax.set_ylabel("Dice loss against unperturbed")
            ax.set_title("Other conditions")
        else:
            items = rotations if panel == "rot" else scales
            for m in methods:
                per = summary["perturbation"].get(m, {})
                kept = [(v, per[c]["dice"]) for v, c in items if c in per]
                ax.plot([v for v, _ in kept], [d for _, d in kept], "o-", label=m)
            if panel == "rot":
                ax.set_xlabel("rotation of the test case (degrees; 0: unperturbed)")
                ax.set_title("Rotation only")
            else:
                ax.set_xscale("log")
                ax.set_xticks([v for v, _ in items], [f"{v:g}" for v, _ in items])
                ax.minorticks_off()
                ax.set_xlabel("scale of the test case (1: unperturbed)")
                ax.set_title("Scale only")
            ax.set_ylabel("mean Dice")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle("Pose perturbation of the test cases")
    fig.tight_layout()
    _figure_path_write(fig, path)


def _pick_cases(rows: list[dict], method: str) -> list[tuple[str, dict]]:
    base = [r for r in _unperturbed(rows) if r["method"] == method and np.isfinite(r["dice"])]
    if not base:
        return []
    # By Dice, ties broken by landmark error (worse error ranks lower).
    order = sorted(base, key=lambda r: (r["dice"], -np.nan_to_num(r["landmark_error_mm"])))
    picks = [("best", order[-1]), ("median", order[len(order) // 2]), ("worst", order[0])]
    return picks


def _slices(volume: np.ndarray, centre: np.ndarray) -> list[np.ndarray]:
    z, y, x = (int(round(c)) for c in centre)
    return [volume[z], volume[:, y], volume[:, :, x]]


def _overlays(picks, cohort, folder: Path, labels, method: str, path: Path) -> None:
    import matplotlib.pyplot as plt

    by_id = {c.case_id: c for c in cohort}
    fig, axes = plt.subplots(len(picks), 3, figsize=(10, 3.4 * len(picks)), squeeze=False)
    for row_axes, (what, row) in zip(axes, picks, strict=True):
        case = by_id[row["case"]]
        image = case.load_image()
        ref = sitk.GetArrayFromImage(select_labels(case.load_label(), labels))
        pred = sitk.GetArrayFromImage(
            read_image(prediction_path(folder / "predictions", method, row["case"]))
        )
        arr = sitk.GetArrayFromImage(image).astype(float)
        centre = np.argwhere(ref).mean(axis=0)
        sz, sy, sx = np.asarray(image.GetSpacing())[::-1]
        aspects = [sy / sx, sz / sx, sz / sy]
        names = ["axial (z)", "coronal (y)", "sagittal (x)"]
        for ax, im, r, p, aspect, name in zip(
            row_axes,
            _slices(arr, centre),
            _slices(ref, centre),
            _slices(pred, centre),
            aspects,
            names,
            strict=True,
        ):
            lo, hi = np.percentile(im, [1, 99])
            ax.imshow(im, cmap="gray", vmin=lo, vmax=hi, aspect=aspect, origin="lower")
            if r.any():
                ax.contour(r, levels=[0.5], colors="lime", linewidths=1.2)
            if p.any():
                ax.contour(p, levels=[0.5], colors="red", linewidths=1.2)
            ax.set_title(f"{name}", fontsize=9)
            ax.axis("off")
        row_axes[0].text(
            -0.05,
            0.5,
            f"{what}: {row['case']}\nDice {row['dice']:.3f}\nLE {row['landmark_error_mm']:.2f} mm",
            transform=row_axes[0].transAxes,
            ha="right",
            va="center",
            fontsize=9,
        )
    fig.suptitle(f"{method}: reference (green) and prediction (red)")
    fig.tight_layout()
    _figure_path_write(fig, path)


def _mesh(mask: sitk.Image):
    import pyvista as pv
    from skimage.measure import marching_cubes

    arr = np.pad(sitk.GetArrayFromImage(mask).astype(np.float32), 1)
    verts, faces, _, _ = marching_cubes(arr, level=0.5)
    points = voxel_to_physical(mask, verts - 1.0)
    cells = np.hstack([np.full((len(faces), 1), 3), faces]).ravel()
    return pv.PolyData(points, cells)


def _surface_png(case, labels, prediction: Path, title: str, path: Path) -> None:
    import pyvista as pv

    reference = _mesh(select_labels(case.load_label(), labels))
    predicted = _mesh(read_image(prediction))
    plotter = pv.Plotter(off_screen=True, window_size=(700, 560))
    plotter.add_mesh(predicted, color="tomato", smooth_shading=True, label="prediction")
    plotter.add_mesh(reference, color="lightgreen", opacity=0.35, label="reference")
    plotter.add_legend()
    plotter.add_text(title, font_size=10)
    plotter.view_isometric()
    with atomic_write(path) as tmp:
        plotter.screenshot(str(tmp))
    plotter.close()


def write_report(
    output_dir: str | os.PathLike,
    cohort=None,
    *,
    labels: Sequence[int] = (1,),
    main_method: str | None = None,
    title: str | None = None,
) -> Path:
    """Write the summary table, summary.json and the figures next to ``cases.csv``.

    Parameters
    ----------
    output_dir : path
        Folder holding ``cases.csv`` (and ``predictions/`` for the overlays).
    cohort : Cohort, optional
        The evaluated cohort: its images and reference labels are drawn in the overlays and
        the surface view. Without it (or without saved predictions) those two are skipped.
    labels : sequence of int
        Labels forming the structure.
    main_method : str, optional
        Method of the overlays and the surface, and the reference of the ratios; default
        "shape_prior" when present, else the first method.
    title : str, optional

    Returns
    -------
    summary_md : pathlib.Path
    """
    import matplotlib

    matplotlib.use("Agg")
    folder = Path(output_dir)
    rows = read_results(folder / "cases.csv")
    if not rows:
        raise InputFileError(
            f"no results in {folder / 'cases.csv'}: run the evaluation first (or check the path)"
        )
    summary = summarise(rows)
    methods = summary["methods"]
    if main_method is not None:
        if main_method not in methods:
            raise InputFileError(f"method {main_method!r} has no results; have {methods}")
        methods = [main_method] + [m for m in methods if m != main_method]
        summary["methods"] = methods
    main = methods[0]
    title = title or f"medseg evaluation ({folder.name})"
    out = folder / "summary.md"
    with atomic_write(out) as tmp:
        tmp.write_text(_markdown(summary, title), encoding="utf-8")
    with atomic_write(folder / "summary.json") as tmp:
        tmp.write_text(_summary_json(rows, summary), encoding="utf-8")
    _boxplots(rows, methods, folder / "landmark_error_boxplot.png")
    if any(_condition_groups(summary)):
        _perturbation_plot(summary, methods, folder / "perturbation.png")
    picks = _pick_cases(rows, main)
    if cohort is not None and picks:
        available = [
            p
            for p in picks
            if prediction_path(folder / "predictions", main, p[1]["case"]).is_file()
        ]
        if len(available) == len(picks):
            _overlays(picks, cohort, folder, tuple(labels), main, folder / "overlays.png")
            median = picks[1][1]
            case = next(c for c in cohort if c.case_id == median["case"])
            _surface_png(
                case,
                tuple(labels),
                prediction_path(folder / "predictions", main, median["case"]),
                f"{main}, median case {median['case']} (Dice {median['dice']:.3f})",
                folder / "surface.png",
            )
    return out
