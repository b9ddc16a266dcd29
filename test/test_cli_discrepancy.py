"""gls-discrepancy run in-process, and the head configuration file it reads."""
import json
import math
import re

import numpy as np
import pytest

from gls_calibration.cli.discrepancy import main
from gls_calibration.geometry.head_config import default_head_config_path, head_config_from_dict, load_head_config
from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.geometry.optics import PhysicalHead

AXIS = np.linspace(-95.0, 95.0, 11)
TARGETS = np.column_stack([np.meshgrid(AXIS, AXIS)[0].ravel(), np.meshgrid(AXIS, AXIS)[1].ravel()])
HEADER = "x_cmd,y_cmd,x_meas,y_meas,t"


def measured_rows(effects, seed=0):
    rng = np.random.default_rng(seed)
    joints = inverse(HeadGeometry(), TARGETS[:, 0], TARGETS[:, 1])
    landed = PhysicalHead(HeadGeometry(), effects).land(joints.alpha_x, joints.alpha_y)[:, :2]
    landed += rng.normal(0.0, 0.01, landed.shape)
    c, s = math.cos(0.4), math.sin(0.4)
    measured = landed @ np.array([[c, s], [-s, c]]) + np.array([12.0, -3.0])
    t = np.arange(len(TARGETS), dtype=float)
    return [f"{q[0]:.6f},{q[1]:.6f},{m[0]:.6f},{m[1]:.6f},{time:.1f}" for q, m, time in zip(TARGETS, measured, t)]


def write_csv(path, rows, header=HEADER):
    path.write_text("\n".join([header] + rows) + "\n")
    return path


@pytest.fixture
def good_csv(tmp_path):
    return write_csv(tmp_path / "marks.csv", measured_rows({"radial_distortion": [3e-7]}))


def test_happy_path_writes_json_report_and_plots(tmp_path, good_csv, capsys):
    out = tmp_path / "out"
    assert main(["--measured", str(good_csv), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "discrepancy.json", "gap_per_step.png", "report.md", "residual_field.png"]
    document = json.loads((out / "discrepancy.json").read_text())
    for key in ("named_effects", "effects", "rms_before_mm", "rms_after_mm", "noise_floor_mm"):
        assert key in document
    assert document["named_effects"][0] == "radial_distortion"
    step = document["effects"][0]
    assert set(step) >= {"name", "parameters", "uncertainty", "indistinguishable_from", "rms_after_mm"}
    assert document["rms_after_mm"] < 0.2 * document["rms_before_mm"]
    report = (out / "report.md").read_text()
    assert "radial_distortion" in report and "residual_field.png" in report and "gap_per_step.png" in report
    assert (out / "residual_field.png").read_bytes()[:4] == b"\x89PNG"
    assert "named effects: radial_distortion" in capsys.readouterr().out


def test_model_file_with_known_effect_and_existing_out_dir(tmp_path):
    csv_path = write_csv(tmp_path / "marks.csv", measured_rows({"galvo_gain_x": [4e-3]}))
    model = tmp_path / "head.yaml"
    model.write_text("/**:\n  ros__parameters:\n    head:\n      working_distance_mm: 490.0\n"
                     "      effects:\n        galvo_gain_x: [0.004]\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    assert main(["--measured", str(csv_path), "--model", str(model), "--out", str(out)]) == 0
    document = json.loads((out / "discrepancy.json").read_text())
    assert document["named_effects"] == []
    assert document["known_effects"] == {"galvo_gain_x": [0.004]}
    assert (out / "keep.txt").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]   # staging removed


def test_nan_rows_are_dropped_with_a_warning(tmp_path, capsys):
    rows = measured_rows({})
    rows[3] = "nan,0,1,2,3"
    rows[7] = rows[7].rsplit(",", 1)[0] + ","      # empty t
    csv_path = write_csv(tmp_path / "marks.csv", rows)
    out = tmp_path / "out"
    assert main(["--measured", str(csv_path), "--out", str(out)]) == 0
    assert "dropped 2 row(s) with NaN or empty values (line(s) 5, 9)" in capsys.readouterr().err
    document = json.loads((out / "discrepancy.json").read_text())
    assert document["point_count"] == len(TARGETS) - 2
    assert document["input"]["dropped_lines"] == [5, 9]


def bad_inputs():
    rows = measured_rows({})
    nan_rows = [row if i < 9 else "nan,nan,nan,nan,nan" for i, row in enumerate(rows)]
    duplicate = rows[:30] + [rows[4]]
    return {
        "missing column": (HEADER.replace(",y_meas", ""), [r.split(",", 4)[0] + "," + ",".join(r.split(",")[1:3]) + ","
                                                           + r.split(",")[4] for r in rows],
                           r"missing column\(s\) y_meas"),
        "non-numeric": (HEADER, rows[:5] + ["1.0,abc,3,4,5"] + rows[6:],
                        r"line 7, column 'y_cmd': 'abc' is not a number"),
        "too few points": (HEADER, rows[:9], r"only 9 valid point\(s\) after dropping 0 row\(s\)"),
        "too few after NaN": (HEADER, nan_rows, r"only 9 valid point\(s\) after dropping \d+ row\(s\)"),
        "duplicate targets": (HEADER, duplicate, r"1 duplicate commanded target\(s\): \(-19, -95\) first on line 6"),
        "ragged row": (HEADER, rows[:5] + ["1,2,3"] + rows[6:], r"line 7 has 3 field\(s\), the header has 5"),
        "infinite": (HEADER, rows[:5] + ["1,2,inf,4,5"] + rows[6:], r"line 7, column 'x_meas': 'inf' is not finite"),
    }


@pytest.mark.parametrize("case", list(bad_inputs()))
def test_bad_csv_exits_2_and_writes_nothing(tmp_path, capsys, case):
    header, rows, message = bad_inputs()[case]
    csv_path = write_csv(tmp_path / "marks.csv", rows, header)
    out = tmp_path / "out"
    assert main(["--measured", str(csv_path), "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert error.startswith("gls-discrepancy: error:")
    assert re.search(message, error), error
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["marks.csv"]


@pytest.mark.parametrize("yaml_text,message", [
    ("head:\n  effects:\n    lens_wobble: [1.0]\n", r"unknown effect 'lens_wobble'"),
    ("head:\n  working_distanse_mm: 480\n", r"unknown head parameter\(s\) 'working_distanse_mm'"),
    ("head:\n  effects:\n    plate_tilt: [0.001]\n", r"effect 'plate_tilt' takes 2 parameter\(s\)"),
    ("head: [1, 2\n", r"cannot parse head configuration"),
])
def test_bad_model_exits_2_and_writes_nothing(tmp_path, good_csv, capsys, yaml_text, message):
    model = tmp_path / "head.yaml"
    model.write_text(yaml_text)
    out = tmp_path / "out"
    assert main(["--measured", str(good_csv), "--model", str(model), "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert "gls-discrepancy: error:" in error
    assert re.search(message, error), error
    assert not out.exists()


def test_missing_files_and_arguments_exit_2(tmp_path, capsys):
    assert main(["--measured", str(tmp_path / "none.csv"), "--out", str(tmp_path / "out")]) == 2
    assert "cannot read" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "out")]) == 2          # argparse: --measured is required
    assert "--measured" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_default_head_config_is_the_published_set_up():
    geometry, effects = load_head_config(default_head_config_path())
    assert geometry == HeadGeometry()
    assert effects.nonzero() == {}


def test_head_config_accepts_dotted_and_plain_layouts():
    dotted = {"/**": {"ros__parameters": {"head.mirror_distance_mm": 12.0, "head.effects.galvo_gain_y": [0.002]}}}
    geometry, effects = head_config_from_dict(dotted)
    assert geometry.mirror_distance_mm == 12.0
    assert geometry.working_distance_mm == 490.0
    assert effects.get("galvo_gain_y") == (0.002,)
    plain = {"head": {"mirror_limit_deg": 12.0, "effects": {"radial_distortion": 1e-7}}}
    geometry, effects = head_config_from_dict(plain)
    assert geometry.mirror_limit_rad == pytest.approx(math.radians(12.0))
    assert effects.get("radial_distortion") == (1e-7,)
    with pytest.raises(ValueError, match=r"head parameter 'focus_range_mm' must be a finite number"):
        head_config_from_dict({"head": {"focus_range_mm": "far"}})
