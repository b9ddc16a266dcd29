"""gls-discrepancy on a run's own fiducials.csv, with an independent floor, outliers and user effects."""
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from gls_calibration.calibration.outcome import deviation_metrics
from gls_calibration.cli.discrepancy import main
from gls_calibration.discrepancy import run_verdict_lines
from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.geometry.optics import PhysicalHead
from gls_calibration.report.files import ReportData, write_report

AXIS = np.linspace(-95.0, 95.0, 15)
TARGETS = np.column_stack([np.meshgrid(AXIS, AXIS)[0].ravel(), np.meshgrid(AXIS, AXIS)[1].ravel()])
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def landed(effects, seed, noise_mm=0.02):
    joints = inverse(HeadGeometry(), TARGETS[:, 0], TARGETS[:, 1])
    points = PhysicalHead(HeadGeometry(), effects).land(joints.alpha_x, joints.alpha_y)[:, :2]
    return points + np.random.default_rng(seed).normal(0.0, noise_mm, points.shape)


def run_fiducials_csv(tmp_path, measured_xy):
    """The fiducials.csv a calibration run writes (report.write_report), 'before' and 'after' stages."""
    deviations = TARGETS - measured_xy
    after = 0.1 * deviations
    write_report(tmp_path / "run", ReportData(
        targets_xy=TARGETS, deviations_before=deviations,
        metrics_before=deviation_metrics(TARGETS, deviations).to_dict(),
        targets_after=TARGETS, deviations_after=after, metrics_after=deviation_metrics(TARGETS, after).to_dict(),
        true_before=deviations))
    return tmp_path / "run" / "fiducials.csv"


def test_a_runs_fiducials_csv_is_accepted_and_outliers_give_its_data_rows(tmp_path):
    measured = landed({"galvo_gain_x": [4e-3]}, seed=1)
    measured[[17, 150]] += np.array([[1.5, 0.0], [0.0, -2.0]])
    path = run_fiducials_csv(tmp_path, measured)
    out = tmp_path / "out"
    assert main(["--measured", str(path), "--out", str(out), "--sigma", "0.02"]) == 0
    document = json.loads((out / "discrepancy.json").read_text())
    assert document["input"]["format"] == "fiducials"
    assert document["point_count"] == len(TARGETS) - 2
    assert document["noise_floor_source"] == "stated"
    assert document["noise_floor_mm"] == pytest.approx(math.sqrt(2) * 0.02)
    assert [o["index"] for o in document["outliers"]] == [17, 150]     # 'before' rows come first in the file
    assert document["outliers"][0]["x_mm"] == pytest.approx(TARGETS[17, 0])
    assert "galvo_gain_x" in document["named_effects"] or any(
        "galvo_gain_x" in step["indistinguishable_from"] for step in document["effects"])
    assert document["verdict"] == "explained"
    report = (out / "report.md").read_text()
    assert "## Verdict" in report and "Outliers (excluded from every fit)" in report and "| 150 |" in report


def test_sigma_column_and_repeats_set_the_floor_source(tmp_path):
    truth = landed({"working_distance": [1.5]}, seed=0, noise_mm=0.0)
    rows = []
    for repeat in range(3):
        measured = truth + np.random.default_rng(10 + repeat).normal(0.0, 0.02, truth.shape)
        rows += [f"{q[0]:.6f},{q[1]:.6f},{m[0]:.6f},{m[1]:.6f},0.02,{repeat}" for q, m in zip(TARGETS, measured)]
    repeats = tmp_path / "repeats.csv"
    repeats.write_text("x_cmd,y_cmd,x_meas,y_meas,sigma,repeat\n" + "\n".join(rows) + "\n")
    assert main(["--measured", str(repeats), "--out", str(tmp_path / "a")]) == 0
    document = json.loads((tmp_path / "a" / "discrepancy.json").read_text())
    assert document["noise_floor_source"] == "repeats"
    assert document["noise_floor"]["repeats"] == 3
    assert document["noise_floor_mm"] == pytest.approx(math.sqrt(2) * 0.02 / math.sqrt(3), rel=0.1)
    single = tmp_path / "single.csv"
    single.write_text("x_cmd,y_cmd,x_meas,y_meas,sigma\n" + "\n".join(r.rsplit(",", 1)[0] for r in rows[:len(TARGETS)]))
    assert main(["--measured", str(single), "--out", str(tmp_path / "b"), "--sigma", "0.5"]) == 0
    document = json.loads((tmp_path / "b" / "discrepancy.json").read_text())
    assert document["noise_floor_source"] == "per_point"          # the column wins over --sigma
    assert document["verdict"] == "explained"


def test_user_effect_from_the_command_line(tmp_path, monkeypatch):
    shutil.copy(EXAMPLES / "user_effects.py", tmp_path / "my_effects.py")
    monkeypatch.chdir(tmp_path)
    module = _load(tmp_path / "my_effects.py")
    effect = module.encoder_nonlinearity_x()
    joints = inverse(HeadGeometry(), TARGETS[:, 0], TARGETS[:, 1])
    from gls_calibration.geometry.effect_table import EffectContext
    extra = effect.deviation(EffectContext(HeadGeometry(), TARGETS, joints.alpha_x, joints.alpha_y, None),
                             np.array([1.5e-4]))
    measured = landed({}, seed=3) + extra
    path = tmp_path / "marks.csv"
    path.write_text("x_cmd,y_cmd,x_meas,y_meas\n" + "\n".join(
        f"{q[0]:.6f},{q[1]:.6f},{m[0]:.6f},{m[1]:.6f}" for q, m in zip(TARGETS, measured)) + "\n")
    assert main(["--measured", str(path), "--out", "without", "--sigma", "0.02"]) == 0
    assert main(["--measured", str(path), "--out", "with", "--sigma", "0.02",
                 "--effects", "my_effects:encoder_nonlinearity_x"]) == 0
    without = json.loads((tmp_path / "without" / "discrepancy.json").read_text())
    with_effect = json.loads((tmp_path / "with" / "discrepancy.json").read_text())
    assert without["verdict"] == "unexplained_structure"
    assert with_effect["verdict"] == "explained"
    assert "encoder_nonlinearity_x" in with_effect["named_effects"]
    assert with_effect["rms_after_mm"] < 0.5 * without["rms_after_mm"]


def _load(path):
    import importlib.util
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("arguments,message", [
    (["--sigma", "-1"], r"--sigma must be a finite number > 0 \(mm\), got -1.0"),
    (["--effects", "nomodule_xyz:f"], r"user effect 'nomodule_xyz:f': cannot import 'nomodule_xyz'"),
    (["--effects", "json"], r"user effect 'json' must be given as module:function"),
    (["--effects", "json:nothing_here"], r"json has no function 'nothing_here'"),
    (["--effects", "json:dumps"], r"missing 1 required positional argument|must return a UserEffect"),
])
def test_bad_options_exit_2_and_write_nothing(tmp_path, capsys, arguments, message):
    import re
    path = tmp_path / "marks.csv"
    measured = landed({}, seed=0)
    path.write_text("x_cmd,y_cmd,x_meas,y_meas\n" + "\n".join(
        f"{q[0]:.6f},{q[1]:.6f},{m[0]:.6f},{m[1]:.6f}" for q, m in zip(TARGETS, measured)) + "\n")
    try:
        code = main(["--measured", str(path), "--out", str(tmp_path / "out")] + arguments)
    except TypeError as error:      # json.dumps() without arguments
        pytest.fail(f"a bad user effect must exit 2, not raise: {error}")
    assert code == 2
    assert re.search(message, capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


def test_repeats_must_hold_the_same_targets(tmp_path, capsys):
    rows = ([f"{q[0]},{q[1]},{q[0]},{q[1]},0" for q in TARGETS]
            + [f"{q[0]},{q[1]},{q[0]},{q[1]},1" for q in TARGETS[:-1]])
    path = tmp_path / "marks.csv"
    path.write_text("x_cmd,y_cmd,x_meas,y_meas,repeat\n" + "\n".join(rows) + "\n")
    assert main(["--measured", str(path), "--out", str(tmp_path / "out")]) == 2
    assert "repeat 1 does not hold the same commanded targets as repeat 0" in capsys.readouterr().err


def test_the_run_report_lines_carry_the_verdict():
    measured = landed({"galvo_gain_y": [3e-3]}, seed=2)
    lines = run_verdict_lines(TARGETS, TARGETS - measured, HeadGeometry())
    assert lines[0].startswith("Discrepancy workflow on the first plate")
    assert any(line.startswith("**Verdict: explained.**") for line in lines)
    assert run_verdict_lines(TARGETS[:5], np.zeros((5, 2)))[0].startswith("Discrepancy verdict: not computed")
