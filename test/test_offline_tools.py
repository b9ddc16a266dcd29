"""gls-correct --calibration and gls-export: complete outputs, flags, exit codes, nothing half written."""
from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from gls_calibration.calibration.record import correction_from_record
from gls_calibration.calibration.record_file import head_geometry, load_record, new_record
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.cli.correct import main as correct_main
from gls_calibration.cli.export import bilinear, main as export_main
from gls_calibration.correction.setpoints import CalibratedRegion
from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.models.rbf import ThinPlateSplineModel


@pytest.fixture(scope="module")
def calibration_file(tmp_path_factory):
    grid = grid_targets(19, 190.0)
    rng = np.random.default_rng(3)
    measured = grid + rng.normal(0.0, 0.3, grid.shape)
    s, t = measured[:, 0] / 95.0, measured[:, 1] / 95.0
    field = np.column_stack([0.6 * s + 0.3 * s ** 3, 0.3 * t - 0.2 * s * s])
    region = CalibratedRegion.from_points(grid)
    record = new_record(
        head=HeadGeometry(), plate_pose={"normal": [0, 0, 1], "centre": [0, 0, 0], "rotation": np.eye(3),
                                         "flatness_rms_mm": 0.0},
        models=[ThinPlateSplineModel(measured, field, 10.0).to_dict()],
        calibrated_region={**region.to_dict(), "taper_mm": 10.0}, hyper_parameters={}, metrics={},
        fiducials={"target_x": grid[:, 0], "target_y": grid[:, 1], "measured_x": measured[:, 0],
                   "measured_y": measured[:, 1], "measured_z": np.zeros(len(grid)),
                   "dx": grid[:, 0] - measured[:, 0], "dy": grid[:, 1] - measured[:, 1]})
    return CalibrationStore(tmp_path_factory.mktemp("store")).save(record)


def write_targets(path, rows, header="x,y,z"):
    path.write_text(header + "\n" + "".join(",".join(map(str, row)) + "\n" for row in rows))
    return path


def test_offline_correction_matches_the_package_and_keeps_unreachable_rows(tmp_path, calibration_file, capsys):
    rows = [(10.0, -20.0, 0.0), (80.0, 60.0, 12.0), (400.0, 0.0, 0.0), (-30.0, 300.0, -6.0), (0.0, 0.0, 5.0)]
    targets = write_targets(tmp_path / "targets.csv", rows)
    out = tmp_path / "corrected.csv"
    assert correct_main(["--calibration", str(calibration_file), str(targets), "--out", str(out)]) == 1
    message = capsys.readouterr().err
    assert "2 of 5 target(s) beyond the mirror limits or the focus range (first: data row 3)" in message
    table = np.genfromtxt(out, delimiter=",", names=True)
    assert table.dtype.names == ("x", "y", "z", "k_x", "k_y", "alpha_x_rad", "alpha_y_rad", "focus_shift_mm",
                                 "inside_calibrated_field", "within_limits", "uncertainty_k2_mm")
    assert table.shape == (5,)
    record = load_record(calibration_file)
    expected = correction_from_record(record, head_geometry(record)).correct(*np.array(rows).T)
    np.testing.assert_array_equal(table["alpha_y_rad"], expected.alpha_y)
    np.testing.assert_array_equal(table["focus_shift_mm"], expected.focus_shift)
    assert table["within_limits"].tolist() == [1, 1, 0, 0, 1]
    assert table["inside_calibrated_field"].tolist() == [1, 1, 0, 0, 1]


@pytest.mark.parametrize("rows, message", [
    ([(1.0, float("nan"), 0.0)], "1 row(s) with NaN or infinite values (first: data row 1)"),
    ([(1.0, 2.0, "inf")], "1 row(s) with NaN or infinite values"),
])
def test_offline_correction_refuses_nan_targets(tmp_path, calibration_file, capsys, rows, message):
    targets = write_targets(tmp_path / "targets.csv", rows)
    assert correct_main(["--calibration", str(calibration_file), str(targets), "--out", str(tmp_path / "o.csv")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o.csv").exists()


@pytest.mark.parametrize("mutate, message", [
    (lambda r: r["models"][0].update(type="neural_net"), "unknown model type 'neural_net'"),
    (lambda r: r["models"][0].pop("affine"), "'affine'"),
    (lambda r: r.update(format_version=7), "format_version 7 is newer than this software reads (up to 2)"),
])
def test_bad_calibration_files_exit_2_naming_the_problem(tmp_path, calibration_file, capsys, mutate, message):
    record = yaml.safe_load(calibration_file.read_text())
    mutate(record)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(record))
    targets = write_targets(tmp_path / "targets.csv", [(1.0, 2.0, 0.0)])
    assert correct_main(["--calibration", str(bad), str(targets), "--out", str(tmp_path / "o.csv")]) == 2
    assert export_main(["--calibration", str(bad), "--out", str(tmp_path / "export")]) == 2
    errors = capsys.readouterr().err
    assert errors.count(message) == 2, errors
    assert not (tmp_path / "o.csv").exists() and not (tmp_path / "export").exists()


def test_unwritable_output_exits_2(tmp_path, calibration_file, capsys):
    targets = write_targets(tmp_path / "targets.csv", [(1.0, 2.0, 0.0)])
    assert correct_main(["--calibration", str(calibration_file), str(targets),
                         "--out", str(tmp_path / "missing" / "o.csv")]) == 2
    assert "does not exist" in capsys.readouterr().err
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    assert export_main(["--calibration", str(calibration_file), "--out", str(blocker / "export")]) == 2
    assert "cannot write" in capsys.readouterr().err
    assert blocker.read_text() == "not a folder"


def test_export_writes_tables_the_interpolation_error_and_the_deviations(tmp_path, calibration_file):
    out = tmp_path / "export"
    assert export_main(["--calibration", str(calibration_file), "--out", str(out), "--pitch", "5",
                        "--z", "0", "10"]) == 0
    archive = np.load(out / "table.npz")
    axis_x, axis_y = archive["axis_x_mm"], archive["axis_y_mm"]
    assert axis_x[0] == -95.0 and axis_x[-1] >= 95.0 and np.allclose(np.diff(axis_x), 5.0)
    assert archive["k_x"].shape == (2, axis_y.size, axis_x.size)
    table = np.genfromtxt(out / "table.csv", delimiter=",", names=True)
    assert table.shape == (2 * axis_x.size * axis_y.size,)
    np.testing.assert_array_equal(table["alpha_x_rad"], archive["alpha_x_rad"].ravel())
    # The table holds the exact correction at its nodes.
    record = load_record(calibration_file)
    exact = correction_from_record(record, head_geometry(record)).correct(table["x"], table["y"], table["z"])
    np.testing.assert_allclose(table["k_y"], exact.y, rtol=0.0, atol=1e-12)
    # The reported worst error is what bilinear interpolation really gives inside the cells (checked here
    # at other points than the tool's), and a finer pitch lowers it.
    summary = json.loads((out / "interpolation_error.json").read_text())
    worst = summary["worst_interpolation_error"][0]["whole_table"]
    rng = np.random.default_rng(0)
    x, y = rng.uniform(axis_x[0], axis_x[-1], 5000), rng.uniform(axis_y[0], axis_y[-1], 5000)
    exact_here = correction_from_record(record, head_geometry(record)).correct(x, y)
    guess = bilinear(archive["k_x"][0], axis_x, axis_y, x, y)
    assert 1e-6 < np.max(np.abs(guess - exact_here.x)) <= 1.5 * worst["corrected_target_mm"]
    finer = tmp_path / "finer"
    assert export_main(["--calibration", str(calibration_file), "--out", str(finer), "--pitch", "2"]) == 0
    finer_worst = json.loads((finer / "interpolation_error.json").read_text())["worst_interpolation_error"][0]
    coarse_inside = summary["worst_interpolation_error"][0]["cells_inside_calibrated_field"]
    assert (finer_worst["whole_table"]["landing_from_interpolated_angles_mm"]
            < worst["landing_from_interpolated_angles_mm"])
    assert (finer_worst["cells_inside_calibrated_field"]["landing_from_interpolated_angles_mm"]
            < coarse_inside["landing_from_interpolated_angles_mm"] <= worst["landing_from_interpolated_angles_mm"])
    deviations = np.genfromtxt(out / "deviations.txt", delimiter=",", names=True)
    assert deviations.dtype.names == ("x", "y", "dx", "dy") and deviations.shape == (361,)
    np.testing.assert_array_equal(deviations["dx"], record["fiducials"]["dx"])
