"""More bad or odd input: identical repeats, structure below a stated floor, effects implausible only
at an early step, a grid smaller than the plate, and the report's list of files."""
import json
from types import SimpleNamespace

import numpy as np
import pytest

from gls_calibration.cli import measure
from gls_calibration.cli.discrepancy import main as discrepancy_main
from gls_calibration.discrepancy import explain, selection, verdict_lines
from gls_calibration.discrepancy.noise_floor import average_repeats
from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.geometry.optics import PhysicalHead
from gls_calibration.report import run_report
from gls_calibration.report.files import ReportData, write_report
from test_cli_discrepancy import TARGETS, measured_rows
import test_cli_measure
from test_cli_measure import _save_npz

scan = test_cli_measure.scan      # module fixture: a rendered 3x3 plate


def _csv(path, header, rows):
    path.write_text(header + "\n" + "\n".join(rows) + "\n")
    return path


def test_identical_repeats_are_bad_input_not_a_crash(tmp_path, capsys):
    rows = [row.rsplit(",", 1)[0] for row in measured_rows({"radial_distortion": [3e-7]})]
    path = _csv(tmp_path / "rep.csv", "x_cmd,y_cmd,x_meas,y_meas,repeat",
                [f"{row},{repeat}" for repeat in (0, 1) for row in rows])
    out = tmp_path / "out"
    assert discrepancy_main(["--measured", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "repeats show no scatter: the noise floor cannot be estimated from them" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_average_repeats_rejects_repeats_identical_up_to_a_rigid_motion():
    points = TARGETS.astype(float)
    c, s = np.cos(0.1), np.sin(0.1)
    moved = points @ np.array([[c, s], [-s, c]]) + np.array([3.0, -1.0])
    with pytest.raises(ValueError, match=r"^repeats show no scatter: the noise floor cannot be estimated"):
        average_repeats(np.stack([points, moved]))
    noisy = points + np.random.default_rng(0).normal(0.0, 0.01, points.shape)
    assert average_repeats(np.stack([points, noisy]))[1] > 0.0


def test_structure_below_a_pessimistic_floor_is_not_reported_as_zero(tmp_path, capsys):
    rows = [row.rsplit(",", 1)[0] + ",0.5" for row in measured_rows({"radial_distortion": [3e-7]})]
    path = _csv(tmp_path / "sigma.csv", "x_cmd,y_cmd,x_meas,y_meas,sigma", rows)
    out = tmp_path / "out"
    assert discrepancy_main(["--measured", str(path), "--out", str(out), "--max-steps", "0"]) == 0
    printed = capsys.readouterr().out
    document = json.loads((out / "discrepancy.json").read_text())
    assert document["verdict"] == "unexplained_structure"
    assert document["noise_floor_mm"] > document["rms_after_mm"]          # below the stated floor ...
    assert document["verdict_detail"]["below_floor"] is True
    assert 0.5 * document["rms_after_mm"] < document["unexplained_rms_mm"] <= document["rms_after_mm"]
    assert "0.0000 mm unexplained" not in printed
    assert f"{document['unexplained_rms_mm']:.4f} mm unexplained (smooth structure below the noise floor)" in printed
    report = (out / "report.md").read_text()
    assert "0.0000 mm RMS" not in report and "remains below the per_point noise floor" in report


def test_effect_implausible_only_at_an_early_step_is_named_not_listed_as_not_named(monkeypatch):
    joints = inverse(HeadGeometry(), TARGETS[:, 0], TARGETS[:, 1])
    landed = PhysicalHead(HeadGeometry(), {"radial_distortion": [3e-7], "galvo_gain_x": [4e-3]}).land(
        joints.alpha_x, joints.alpha_y)[:, :2]
    measured = landed + np.random.default_rng(3).normal(0.0, 0.01, landed.shape)
    real = selection.implausible_values

    def implausible_alone(predict, model):   # galvo_gain_x is implausible only while fitted on its own (step 1)
        return ["out of range alone"] if model.names == ("galvo_gain_x",) else real(predict, model)
    monkeypatch.setattr(selection, "implausible_values", implausible_alone)
    result = explain(TARGETS, measured, sigma_mm=0.01)
    assert result.steps[0].name != "galvo_gain_x"
    assert "galvo_gain_x" in result.named_effects
    assert "galvo_gain_x" not in [entry.name for entry in result.implausible]
    assert not any("physically implausible" in line and "galvo_gain_x" in line for line in verdict_lines(result))
    assert not any("implausible" in note and "galvo_gain_x" in note for note in result.notes)


def test_grid_smaller_than_the_plate_warns_and_never_counts_negative_missing(tmp_path, scan, capsys):  # noqa: F811
    xyz, intensity, _ = scan
    cloud = _save_npz(tmp_path / "scan.npz", xyz, intensity)
    out = tmp_path / "out"
    assert measure.main(["--cloud", str(cloud), "--grid", "1", "--size", "40", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["accepted"] > 1
    assert summary["missing"] == 0 and summary["extra"] == summary["accepted"] - 1
    err = capsys.readouterr().err
    assert (f"warning: {summary['accepted']} fiducials accepted, more than the 1 of a 1x1 grid: check --grid"
            in err)


def test_report_files_section_lists_extra_files(tmp_path):
    targets = TARGETS[:20].astype(float)
    deviations = np.full_like(targets, 0.01)
    from gls_calibration.calibration.outcome import deviation_metrics
    write_report(tmp_path / "r", ReportData(targets_xy=targets, deviations_before=deviations,
                                            metrics_before=deviation_metrics(targets, deviations).to_dict(),
                                            extra_files=("- `training.csv`: training data.",)))
    files = (tmp_path / "r" / "report.md").read_text().split("## Files", 1)[1]
    assert "`fiducials.csv`" in files and "`training.csv`: training data." in files


def test_main_jobs_report_lists_training_csv_and_the_store(tmp_path, monkeypatch):
    captured = {}
    monkeypatch.setattr(run_report, "ReportData", lambda **fields: fields)
    monkeypatch.setattr(run_report, "write_report", lambda out_dir, data: captured.update(data))
    monkeypatch.setattr(run_report, "run_verdict_lines", lambda *args, **kwargs: ())
    monkeypatch.setattr(run_report, "measurement_lines", lambda summary: ())
    monkeypatch.setattr(run_report, "training_csv_text", lambda run: "x_cmd,y_cmd,z_cmd,x_meas,y_meas\n")
    first = SimpleNamespace(paired_targets_xy=TARGETS, deviations=TARGETS * 0, metrics=None,
                            true_deviations=None, true_metrics=None)
    outcome = SimpleNamespace(runs=[first], validation=None, candidate=None, message="done")
    summary = SimpleNamespace(to_dict=lambda: {}, iteration_rms_mm=())
    (tmp_path / "calibrations").mkdir()
    run_report.write_outcome_report(tmp_path, outcome, summary)
    listed = "\n".join(captured["extra_files"])
    assert "`training.csv`" in listed and "`calibrations/`" in listed
    assert (tmp_path / "training.csv").exists()
