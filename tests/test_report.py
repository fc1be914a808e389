"""The report folder: summary table, summary.json, figures; run_evaluation end to end."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
from test_crossval import ThresholdMethod, tiny_cohort

from medseg.datasets import Cohort
from medseg.errors import CohortError, InputFileError, LabelError, ParameterError
from medseg.evaluation import run_evaluation
from medseg.evaluation.methods import MethodSpec
from medseg.evaluation.report import summarise, write_report
from medseg.evaluation.results import COLUMNS

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _row(method, case, dice, lm, *, condition="acquired", deg=0.0, scale=1.0, hd95=1.0,
         gap=math.nan):  # fmt: skip
    return {
        "method": method,
        "fold": 0,
        "case": case,
        "subject": case,
        "perturbation": condition,
        "perturbation_deg": deg,
        "scale": scale,
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
    _row("shape_prior", "a", 0.5, 9.0, condition="rot45", deg=45.0),
    _row("asm", "a", 0.1, 20.0, condition="rot45", deg=45.0),
    _row("shape_prior", "a", 0.6, 4.0, condition="rot90", deg=90.0),
    _row("shape_prior", "a", 0.85, 1.5, condition="scale0.8", scale=0.8),
    _row("shape_prior", "b", 0.55, 2.5, condition="scale1.25", scale=1.25),
    # pad_zeros and random rotate by 0 and ~20 degrees: told apart by their names only
    _row("shape_prior", "a", 0.88, 1.0, condition="pad_zeros"),
    _row("shape_prior", "b", 0.68, 2.0, condition="pad_zeros"),
    _row("asm", "b", 0.5, 6.0, condition="pad_zeros"),
    _row("shape_prior", "a", 0.7, 3.0, condition="random", deg=20.0, scale=1.1),
    _row("shape_prior", "b", 0.4, 3.0, condition="random", deg=30.0, scale=0.9),
    _row("asm", "a", 0.2, 9.0, condition="random", deg=20.0, scale=1.1),
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
    per_sp, per_asm = s["perturbation"]["shape_prior"], s["perturbation"]["asm"]
    assert set(per_sp) == {"acquired", "rot45", "rot90", "scale0.8", "scale1.25", "pad_zeros",
                           "random"}  # fmt: skip
    assert set(per_asm) == {"acquired", "rot45", "pad_zeros", "random"}
    assert per_asm["rot45"]["dice"] == pytest.approx(0.1)
    assert per_sp["acquired"]["landmark_error_mm"] == pytest.approx(1.5)
    assert per_sp["acquired"]["dice_loss"] == 0.0 and per_sp["acquired"]["n"] == 2
    # The loss is paired by case: (0.9 - 0.7 + 0.7 - 0.4) / 2 for random, ...
    assert per_sp["random"]["dice_loss"] == pytest.approx(0.25)
    assert per_sp["random"]["angle_deg"] == pytest.approx(25.0)
    assert per_sp["random"]["scale"] == pytest.approx(1.0)
    assert per_sp["pad_zeros"]["dice_loss"] == pytest.approx(0.02)
    assert per_sp["scale1.25"]["dice_loss"] == pytest.approx(0.15)  # case b only
    # ... and only over the cases with both rows (asm's pad_zeros: case b)
    assert per_asm["pad_zeros"]["dice_loss"] == pytest.approx(0.3)
    assert per_asm["pad_zeros"]["dice"] == pytest.approx(0.5) and per_asm["pad_zeros"]["n"] == 1


def test_report_files(tmp_path):
    _write_csv(tmp_path, ROWS)
    out = write_report(tmp_path)
    text = out.read_text(encoding="utf-8")
    assert "| shape_prior | 2 | 0.800 ± 0.100 |" in text
    assert "- `asm`: 2.67 x" in text  # 4.0 / 1.5
    # medians (asm's infinite HD95 skipped, as in the means)
    assert (
        "| shape_prior | 0.800 | 1.000 | 0.500 |" in text
        and "| asm | 0.700 | 1.000 | 0.500 |" in text
    )
    assert "## Pose perturbation" in text
    lines = text.splitlines()
    # by rotation angle: 0 (unperturbed), 45, 90
    rotation = lines.index("| method | 0 deg | 45 deg | 90 deg |")
    assert lines[rotation + 2 : rotation + 4] == [
        "| shape_prior | 0.800 | 0.500 | 0.600 |",
        "| asm | 0.700 | 0.100 | - |",
    ]
    # by scale, 1 the unperturbed case
    scale = lines.index("| method | 0.8 | 1 | 1.25 |")
    assert lines[scale + 2 : scale + 4] == [
        "| shape_prior | 0.850 | 0.800 | 0.550 |",
        "| asm | - | 0.700 | - |",
    ]
    # one row per other condition, with the loss against the unperturbed case
    other = lines.index("| condition | shape_prior | asm |")
    assert lines[other + 2 : other + 4] == [
        "| pad_zeros | 0.780 (loss 0.020) | 0.500 (loss 0.300) |",
        "| random | 0.550 (loss 0.250) | 0.200 (loss 0.400) |",
    ]
    assert len(lines) == other + 4  # the last table

    raw = (tmp_path / "summary.json").read_text(encoding="utf-8")
    assert "NaN" not in raw and "Infinity" not in raw
    data = json.loads(raw)
    assert raw == json.dumps(data, indent=2, sort_keys=True)
    assert {"metric_per_case", "mean", "foreground_mean"} <= set(data)
    assert len(data["metric_per_case"]) == len(ROWS)
    assert data["metric_per_case"][-1]["perturbation"] == "random"
    assert set(data["perturbation"]["asm"]) == {"acquired", "rot45", "pad_zeros", "random"}
    assert data["perturbation"]["shape_prior"]["random"]["dice_loss"] == pytest.approx(0.25)
    # the unperturbed table is over the unperturbed rows only (not pad_zeros at 0 degrees)
    assert data["mean"]["asm"]["dice"] == pytest.approx(0.7)
    assert data["mean"]["asm"]["gap"] is None
    assert data["mean"]["shape_prior"]["dice"] == pytest.approx(0.8)
    assert data["metric_per_case"][2]["hd95"] is None  # inf -> null
    for name in ("landmark_error_boxplot.png", "perturbation.png"):
        assert (tmp_path / name).read_bytes()[:8] == PNG_MAGIC
    # No cohort: no overlays, no surface view.
    assert not (tmp_path / "overlays.png").exists()


def test_report_without_perturbation_has_no_study(tmp_path):
    _write_csv(tmp_path, [r for r in ROWS if r["perturbation"] == "acquired"])
    text = write_report(tmp_path).read_text(encoding="utf-8")
    assert "Pose perturbation" not in text
    assert not (tmp_path / "perturbation.png").exists()
    data = json.loads((tmp_path / "summary.json").read_text(encoding="utf-8"))
    assert set(data["perturbation"]["asm"]) == {"acquired"}


def test_report_of_only_other_conditions(tmp_path):
    rows = [r for r in ROWS if r["perturbation"] in ("acquired", "random")]
    _write_csv(tmp_path, rows)
    text = write_report(tmp_path).read_text(encoding="utf-8")
    assert "by rotation angle" not in text and "by scale" not in text
    assert "| random | 0.550 (loss 0.250) | 0.200 (loss 0.400) |" in text
    assert (tmp_path / "perturbation.png").read_bytes()[:8] == PNG_MAGIC


def test_report_without_results_is_a_clear_error(tmp_path):
    with pytest.raises(InputFileError, match="no results"):
        write_report(tmp_path)


def _fake_methods():
    return [MethodSpec(ThresholdMethod, {}, {"thresh": {}, "shifted": {"offset": 1.0}})]


def test_run_evaluation_end_to_end(tmp_path):
    cohort = tiny_cohort(n_subjects=6, per_subject=1)
    out = run_evaluation(
        cohort,
        tmp_path / "report",
        methods=_fake_methods(),
        seed=2,
        perturbation=("rot30", "scale0.9", "pad_noise"),
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
    conditions = {"acquired", "rot30", "scale0.9", "pad_noise"}
    assert set(data["perturbation"]["thresh"]) == conditions
    assert all(v["n"] == len(cohort) for v in data["perturbation"]["thresh"].values())
    assert data["perturbation"]["thresh"]["rot30"]["angle_deg"] == pytest.approx(30.0)
    rows = list(csv.DictReader((out / "cases.csv").open()))
    assert len(rows) == 2 * len(cohort) * 4
    # the loss is the paired mean of the rows: acquired minus perturbed Dice, case by case
    dice = {(r["case"], r["perturbation"]): float(r["dice"]) for r in rows
            if r["method"] == "shifted"}  # fmt: skip
    for name in ("rot30", "scale0.9"):
        loss = np.mean([dice[(c.case_id, "acquired")] - dice[(c.case_id, name)] for c in cohort])
        assert data["perturbation"]["shifted"][name]["dice_loss"] == pytest.approx(loss)
        assert abs(loss) < 0.05
    text = (out / "summary.md").read_text(encoding="utf-8")
    assert "| method | 0 deg | 30 deg |" in text and "| method | 0.9 | 1 |" in text
    assert "| pad_noise |" in text


def test_run_evaluation_refuses_bad_input_before_work(tmp_path):
    with pytest.raises(ParameterError, match="'rot-1'"):
        run_evaluation(tiny_cohort(n_subjects=6, per_subject=1), tmp_path / "p",
                       methods=_fake_methods(), perturbation=("random", "rot-1"))  # fmt: skip
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
    assert not any((tmp_path / d).exists() for d in "abcp")


def test_the_quality_score_is_scored_against_the_failed_cases(tmp_path):
    from medseg.evaluation.flagging import flagging_scores

    dice = [0.9, 0.85, 0.6, 0.88, 0.7, 0.82]
    quality = [0.5, 1.0, 4.0, 3.5, 2.0, 0.2]  # the two failures: 4.0 and 2.0; 3.5 a false alarm
    rows = [
        _row("shape_prior", f"c{i}", d, 1.0) | {"quality": q}
        for i, (d, q) in enumerate(zip(dice, quality, strict=True))
    ]
    rows += [_row("asm", f"c{i}", d, 1.0) for i, d in enumerate(dice)]  # no score: left out
    scores = flagging_scores(rows, threshold=3.0)
    assert set(scores) == {"shape_prior"}
    # failures {4.0, 2.0} against {0.5, 1.0, 3.5, 0.2}: 7 of the 8 pairs ordered
    assert scores["shape_prior"] == {
        "n": 6, "failed": 2, "auc": 7 / 8, "flagged": 2, "flagged_failed": 1
    }  # fmt: skip
    # no failure: no AUC, not a made-up 0.5
    assert math.isnan(flagging_scores(rows, failure_dice=0.5)["shape_prior"]["auc"])
    _write_csv(tmp_path, rows)
    write_report(tmp_path)
    text = (tmp_path / "summary.md").read_text(encoding="utf-8")
    assert "Quality score against failure" in text
    data = json.loads((tmp_path / "summary.json").read_text(encoding="utf-8"))
    assert set(data["flagging"]) == {"shape_prior"} and data["flagging"]["shape_prior"]["n"] == 6
