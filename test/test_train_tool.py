"""gls-train on the training.csv of a calibrate run reproduces the run's calibration (ideal simulated cell)."""
from __future__ import annotations

import asyncio
import dataclasses

import numpy as np
import pytest

from gls_calibration.calibration import procedure
from gls_calibration.calibration.record import build_record, correction_from_record, save_candidate
from gls_calibration.calibration.record_file import head_geometry, load_record
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.cli.train import main as train_main
from gls_calibration.report.run_report import training_csv_text
from gls_calibration.simulation.direct_cell import DirectCell
from gls_calibration.simulation.world import SimulatedCell, load_sim_config


@pytest.mark.slow
def test_training_from_the_run_reports_csv_reproduces_the_saved_calibration(tmp_path, capsys):
    config = load_sim_config()
    config = dataclasses.replace(config, scanner=dataclasses.replace(config.scanner, line_length_mm=120.0),
                                 sweep_length_mm=110.0, scanner_to_gls=None)
    cell = DirectCell(SimulatedCell(config), CalibrationStore(tmp_path / "store"))
    settings = cell.settings(grid_per_side=7, grid_size_mm=90.0, plain_sweeps=1, plain_sweep_step_mm=2.0)

    def save(runs, models):
        return save_candidate(cell.store, build_record(config.geometry, settings, runs, models, []), config.geometry)

    outcome = asyncio.run(procedure.calibrate(cell, settings, iterations=1, validate=False, force=True,
                                              want_truth=False, progress=lambda *args: None, save_candidate=save))
    training = tmp_path / "training.csv"
    training.write_text(training_csv_text(outcome.runs[0]))
    out = tmp_path / "trained.yaml"
    assert train_main(["--measured", str(training), "--out", str(out)]) == 0, capsys.readouterr().err
    assert (tmp_path / "trained.yaml.report.md").exists()
    original = load_record(outcome.candidate.path)
    retrained = load_record(out)
    assert retrained["models"][0]["type"] == original["models"][0]["type"]
    plane = original["calibrated_region"]["plane_z_mm"]
    assert retrained["calibrated_region"]["plane_z_mm"] == pytest.approx(plane, abs=1e-12)
    rng = np.random.default_rng(0)
    # The run's region is the grid padded by the ring radius, gls-train's the box of the commanded
    # targets (+-45 mm): compare where Q' lies inside both at either height.
    x, y = rng.uniform(-44.0, 44.0, (2, 3000))
    for z in (plane, plane + 10.0):
        first = correction_from_record(original, head_geometry(original)).correct(x, y, np.full(x.size, z))
        second = correction_from_record(retrained, head_geometry(retrained)).correct(x, y, np.full(x.size, z))
        difference = np.hypot(first.x - second.x, first.y - second.y)
        assert np.max(difference) <= 1e-3       # 1 um
        assert np.max(np.abs(first.x - x)) > 0.05                                      # it does correct


@pytest.mark.parametrize("text, message", [
    ("x_cmd,y_cmd,x_meas\n1,2,3\n", "missing column(s) y_meas"),
    ("x_cmd,y_cmd,x_meas,y_meas\n" + "1,2,3,4\n" * 12 + "1,nan,3,4\n",
     "1 row(s) with NaN or infinite values (first: data row 13)"),
    ("x_cmd,y_cmd,x_meas,y_meas\n1,2,3,4\n", "1 row(s); at least 10 measured fiducials are needed"),
    ("x_cmd,y_cmd,x_meas,y_meas\n" + "1,2,3,x\n" * 12, "non-numeric value"),
])
def test_gls_train_refuses_bad_measurements(tmp_path, capsys, text, message):
    measured = tmp_path / "measured.csv"
    measured.write_text(text)
    assert train_main(["--measured", str(measured), "--out", str(tmp_path / "c.yaml")]) == 2
    assert message in capsys.readouterr().err
    assert sorted(path.name for path in tmp_path.iterdir()) == ["measured.csv"]


def test_gls_train_unwritable_output_exits_2(tmp_path, capsys):
    measured = tmp_path / "measured.csv"
    grid = np.array([(x, y) for x in (-20.0, 0.0, 20.0, 40.0) for y in (-20.0, 0.0, 20.0)])
    measured.write_text("x_cmd,y_cmd,x_meas,y_meas\n" + "".join(f"{x},{y},{x * 1.001},{y}\n" for x, y in grid))
    assert train_main(["--measured", str(measured), "--out", str(tmp_path / "nowhere" / "c.yaml")]) == 2
    assert "does not exist" in capsys.readouterr().err
