"""The report folder: summary table, summary.json, figures; run_evaluation end to end."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
from test_crossval import ThresholdMethod, tiny_cohort

from medseg.datasets import Cohort
from medseg.errors import CohortError, InputFileError, LabelError
from medseg.evaluation import run_evaluation
from medseg.evaluation.methods import MethodSpec
from medseg.evaluation.report import summarise, write_report
from medseg.evaluation.results import COLUMNS

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _row(method, case, dice, lm, *, deg=0.0, hd95=1.0, gap=math.nan):
    return {
        "method": method,
        "fold": 0,
        "case": case,
        "subject": case,
        "perturbation_deg": deg,
        "scale": 1.0,
        "dice": dice,
        "hd95": hd95,
        "assd": 0.5,
        "landmark_error_mm": lm,
        "landmark_error_vox": lm / 2,
        "gap": gap,
        "seconds": 1.0,
        "fit_seconds": 2.0,
    }


def _write_csv(folder, rows):
    folder.mkdir(parents=True, exist_ok=True)
    with (folder / "cases.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS)
        writer.writeheader()
        for r in rows:
            writer.writerow({k: repr(v) if isinstance(v, float) else v for k, v in r.items()})


ROWS = [
    _row("shape_prior", "a", 0.9, 1.0, gap=0.01),
    _row("shape_prior", "b", 0.7, 2.0, gap=0.03),
    _row("asm", "a", 0.6, 3.0, hd95=math.inf),
    _row("asm", "b", 0.8, 5.0),
    _row("shape_prior", "a", 0.5, 9.0, deg=45.0),
    _row("asm", "a", 0.1, 20.0, deg=45.0),
]


def test_summary_statistics_by_hand():
    s = summarise(ROWS)
    assert s["methods"] == ["shape_prior", "asm"]
    sp, asm = s["stats"]["shape_prior"], s["stats"]["asm"]
    assert sp["dice"]["mean"] == pytest.approx(0.8) and sp["dice"]["n"] == 2
    assert sp["dice"]["std"] == pytest.approx(0.1)
    assert sp["gap"]["mean"] == pytest.approx(0.02)
    assert asm["landmark_error_mm"]["mean"] == pytest.approx(4.0)
    # inf HD95 is not averaged in, and counted as not finite.
    assert asm["hd95"]["mean"] == pytest.approx(1.0) and asm["hd95"]["n_finite"] == 1
    assert math.isnan(asm["gap"]["mean"])
    assert s["perturbation"]["asm"]["45"]["dice"] == pytest.approx(0.1)
    assert s["perturbation"]["shape_prior"]["0"]["landmark_error_mm"] == pytest.approx(1.5)


def test_report_files(tmp_path):
    _write_csv(tmp_path, ROWS)
    out = write_report(tmp_path)
    text = out.read_text(encoding="utf-8")
    assert "| shape_prior | 2 | 0.800 ± 0.100 |" in text
    assert "- `asm`: 2.67 x" in text  # 4.0 / 1.5
    assert "## Pose perturbation" in text and "| asm | 0.700 / 4.00 | 0.100 / 20.00 |" in text

    raw = (tmp_path / "summary.json").read_text(encoding="utf-8")
    assert "NaN" not in raw and "Infinity" not in raw
    data = json.loads(raw)
    assert raw == json.dumps(data, indent=2, sort_keys=True)
    assert {"metric_per_case", "mean", "foreground_mean"} <= set(data)
    assert len(data["metric_per_case"]) == len(ROWS)
    assert data["mean"]["asm"]["gap"] is None
    assert data["mean"]["shape_prior"]["dice"] == pytest.approx(0.8)
    assert data["metric_per_case"][2]["hd95"] is None  # inf -> null
    for name in ("landmark_error_boxplot.png", "perturbation.png"):
        assert (tmp_path / name).read_bytes()[:8] == PNG_MAGIC
    # No cohort: no overlays, no surface view.
    assert not (tmp_path / "overlays.png").exists()


def test_report_without_results_is_a_clear_error(tmp_path):
    with pytest.raises(InputFileError, match="no results"):
        write_report(tmp_path)


def _fake_methods():
    return [MethodSpec(ThresholdMethod, {}, {"thresh": {}, "shifted": {"offset": 1.0}})]


def test_run_evaluation_end_to_end(tmp_path):
    cohort = tiny_cohort(n_subjects=6, per_subject=1)
    out = run_evaluation(
        cohort, tmp_path / "report", methods=_fake_methods(), seed=2, perturbation=(30,)
    )
    names = {p.name for p in out.iterdir()}
    assert {
        "cases.csv",
        "run.json",
        "summary.md",
        "summary.json",
        "landmark_error_boxplot.png",
        "perturbation.png",
        "overlays.png",
        "surface.png",
        "predictions",
    } <= names
    for name in ("overlays.png", "surface.png"):
        assert (out / name).read_bytes()[:8] == PNG_MAGIC
    predictions = sorted((out / "predictions" / "thresh").iterdir())
    assert [p.name for p in predictions] == [f"{c.case_id}.nii.gz" for c in cohort]
    data = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert data["mean"]["thresh"]["dice"] == pytest.approx(1.0)
    assert np.isfinite(data["mean"]["shifted"]["landmark_error_mm"])


def test_run_evaluation_refuses_bad_input_before_work(tmp_path):
    with pytest.raises(CohortError, match="empty"):
        run_evaluation(Cohort(cases=[]), tmp_path / "a", methods=_fake_methods())
    with pytest.raises(CohortError, match="single subject"):
        run_evaluation(
            tiny_cohort(n_subjects=1, per_subject=6), tmp_path / "b", methods=_fake_methods()
        )
    with pytest.raises(LabelError, match="occur in no case"):
        run_evaluation(
            tiny_cohort(n_subjects=6, per_subject=1),
            tmp_path / "c",
            methods=_fake_methods(),
            labels=(3,),
        )
    assert not any((tmp_path / d).exists() for d in "abc")
