"""docs/calibration-format.md: its standalone evaluator agrees with the package; bad files are named."""
from pathlib import Path
import re

import numpy as np
import pytest
import yaml

from gls_calibration.calibration.record import correction_from_record
from gls_calibration.calibration.record_file import head_geometry, load_record, new_record
from gls_calibration.calibration.store import CalibrationStore
from gls_calibration.correction.setpoints import CalibratedRegion
from gls_calibration.fiducials.targets import grid_targets
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.models.physical_model import SumModel
from gls_calibration.models.rbf import OLSRBFNetwork, ThinPlateSplineModel

DOC = Path(__file__).resolve().parent.parent / "docs" / "calibration-format.md"


def doc_evaluator() -> dict:
    """The python block under '## Standalone evaluator', executed on its own (no package import)."""
    text = DOC.read_text(encoding="utf-8")
    section = text.split("## Standalone evaluator", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert len(code.strip().splitlines()) <= 65   # correct() and, since issue 30, uncertainty()
    assert "gls_calibration" not in code.replace("needs the gls_calibration ray trace", "")
    namespace: dict = {}
    exec(compile(code, str(DOC), "exec"), namespace)
    return namespace


def field(points):
    s, t = points[:, 0] / 95.0, points[:, 1] / 95.0
    return np.column_stack([0.6 * s + 0.3 * s ** 3 + 0.1 * s * t + 0.2 * s * (s * s + t * t),
                            0.3 * t - 0.2 * s * s + 0.15 * t ** 3])


def stored_calibration(tmp_path, models, plane_z_mm=0.3, taper_mm=10.0) -> dict:
    """A calibration saved to a store and read back as a parsed file."""
    grid = grid_targets(19, 190.0)
    region = CalibratedRegion.from_points(grid, plane_z_mm)
    zeros = np.zeros(len(grid))
    record = new_record(
        head=HeadGeometry(), plate_pose={"normal": [0, 0, 1], "centre": [0, 0, plane_z_mm], "rotation": np.eye(3),
                                         "flatness_rms_mm": 0.0},
        models=[model.to_dict() for model in models],
        calibrated_region={**region.to_dict(), "taper_mm": taper_mm}, hyper_parameters={}, metrics={},
        fiducials={"target_x": grid[:, 0], "target_y": grid[:, 1], "measured_x": grid[:, 0],
                   "measured_y": grid[:, 1], "measured_z": zeros, "dx": zeros, "dy": zeros})
    path = CalibrationStore(tmp_path).save(record)
    return load_record(path).to_dict()


def queries(count=2000, seed=0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-125.0, 125.0, (count, 2))       # inside, in the taper and beyond it
    xy[:min(count, 90)] = grid_targets(19, 190.0)[:min(count, 90)]   # on centres: r = 0 in the kernel
    return xy[:, 0], xy[:, 1], rng.uniform(-25.0, 25.0, count)


@pytest.mark.parametrize("kind, count", [("tps", 2000), ("ols", 2000), ("sum", 2000), ("none", 2000),
                                         ("tps", 12_000)])       # a batch large enough for the spline's tiles
def test_the_documented_evaluator_agrees_with_the_package(tmp_path, kind, count):
    grid = grid_targets(19, 190.0)
    rng = np.random.default_rng(1)
    measured = grid + rng.normal(0.0, 0.01, grid.shape)
    tps = ThinPlateSplineModel(measured, field(measured), smoothing=10.0)
    ols = OLSRBFNetwork(grid, 0.1 * field(grid[:, ::-1]), 35.0, 0.0005)
    models = {"tps": [tps], "ols": [ols, tps], "sum": [SumModel([ols, tps])], "none": []}[kind]
    record = stored_calibration(tmp_path, models, taper_mm=0.0 if kind == "ols" else 10.0)
    x, y, z = queries(count)
    package = correction_from_record(record, head_geometry(record)).correct(x, y, z)
    evaluated = doc_evaluator()["correct"](yaml.safe_load(yaml.safe_dump(record)), x, y, z)
    for mine, theirs in zip(evaluated, (package.x, package.y, package.alpha_x, package.alpha_y,
                                        package.focus_shift)):
        np.testing.assert_allclose(mine, theirs, rtol=0.0, atol=1e-9)
    if models:
        assert np.max(np.abs(package.x - x)) > 0.1                  # the models really correct


def test_the_single_target_path_agrees_with_the_documented_evaluator(tmp_path):
    grid = grid_targets(19, 190.0)
    record = stored_calibration(tmp_path, [ThinPlateSplineModel(grid, field(grid))])
    correction = correction_from_record(record, head_geometry(record))
    evaluate = doc_evaluator()["correct"]
    for x, y, z in zip(*queries(40, seed=2)):
        one = correction.correct([x], [y], [z])
        expected = evaluate(record, np.array([x]), np.array([y]), np.array([z]))
        np.testing.assert_allclose([one.x[0], one.y[0], one.alpha_x[0], one.alpha_y[0], one.focus_shift[0]],
                                   [value[0] for value in expected], rtol=0.0, atol=1e-9)


def test_a_format_version_1_file_still_loads(tmp_path):
    grid = grid_targets(19, 190.0)
    spline = ThinPlateSplineModel(grid, field(grid), smoothing=10.0)
    record = stored_calibration(tmp_path, [spline], plane_z_mm=0.0)
    record["format_version"] = 1
    record["models"] = [{"type": "thin_plate_spline", "smoothing": 10.0, "points": grid.tolist(),
                         "values": field(grid).tolist()}]
    record["calibrated_region"] = {key: record["calibrated_region"][key] for key in ("type", "x_min", "x_max",
                                                                                     "y_min", "y_max")}
    old = tmp_path / "old.yaml"
    old.write_text(yaml.safe_dump(record))
    loaded = load_record(old)
    x, y, z = queries(300)
    expected = correction_from_record(stored_calibration(tmp_path / "new", [spline], plane_z_mm=0.0),
                                      HeadGeometry()).correct(x, y, z)
    result = correction_from_record(loaded, head_geometry(loaded)).correct(x, y, z)
    np.testing.assert_allclose(result.alpha_x, expected.alpha_x, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(result.x, expected.x, rtol=0.0, atol=1e-9)


def test_a_record_is_dumped_once_and_as_a_plain_copy_of_it_would_be():
    """``dump_record`` of a CalibrationRecord: the text of its plain copy, made at the first call only."""
    from gls_calibration.calibration.record_file import CalibrationRecord, dump_record
    from test_persistence import make_record

    record = make_record()
    record = record if isinstance(record, CalibrationRecord) else CalibrationRecord(record)
    text = dump_record(record)
    assert text == dump_record(record.to_dict()) and dump_record(record) is text
