"""The cell frames file: what it holds, and every malformed file refused with a message naming the problem."""
import copy

import numpy as np
import pytest
import yaml

from gls_calibration.common.config_files import config_path
from gls_calibration.scan.cell_frames import cell_frames_from_dict, load_cell_frames
from gls_calibration.simulation.recording_cell import SIM_FLANGE_TO_SENSOR, base_to_gls
from gls_calibration.simulation.world import load_sim_config


def _document():
    return yaml.safe_load(config_path("cell_frames.yaml").read_text())


def test_shipped_file_is_the_simulated_cell():
    """The shipped file holds the simulated cell's hand-eye and the head's CAD mounting of sim.yaml."""
    frames = load_cell_frames()
    assert (frames.base, frames.flange, frames.sensor, frames.gls) == ("robot_base", "flange", "scanner_optical", "gls")
    np.testing.assert_allclose(frames.flange_to_sensor, SIM_FLANGE_TO_SENSOR, atol=1e-12)
    np.testing.assert_allclose(frames.base_to_gls, base_to_gls(load_sim_config()), atol=1e-9)


def test_metres_become_millimetres():
    document = _document()
    document["flange_to_sensor"] = {"translation_m": [0.001, -0.002, 0.5], "rpy_rad": [0.0, 0.0, 0.0]}
    np.testing.assert_allclose(cell_frames_from_dict(document).flange_to_sensor[:3, 3], [1.0, -2.0, 500.0])


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.pop("base_to_gls"), "missing key(s) cell.base_to_gls"),
    (lambda d: d.update(extra=1), "unknown key(s) cell.extra"),
    (lambda d: d["frames"].pop("sensor"), "missing key(s) frames.sensor"),
    (lambda d: d["frames"].update(sensor=""), "frames.sensor must be a non-empty frame name"),
    (lambda d: d["frames"].update(sensor="/scanner"), "frames.sensor must be a non-empty frame name"),
    (lambda d: d["frames"].update(sensor="flange"), "frames must be four different names"),
    (lambda d: d["flange_to_sensor"].update(translation_m=[40.0, 0.0, 18.0]), None),
    (lambda d: d["flange_to_sensor"].update(translation_m=[400.0, 0.0, 180.0]),
     "flange_to_sensor.translation_m [400.0, 0.0, 180.0] is beyond 100 m: it must be in metres"),
    (lambda d: d["flange_to_sensor"].update(rpy_rad=[0.0, 0.0]), "flange_to_sensor.rpy_rad must be a list of 3"),
    (lambda d: d["base_to_gls"].update(rpy_rad=[0.0, float("nan"), 0.0]), "base_to_gls.rpy_rad must be a list of 3"),
    (lambda d: d["base_to_gls"].update(rpy_rad=[0.0, True, 0.0]), "base_to_gls.rpy_rad must be a list of 3"),
    (lambda d: d["base_to_gls"].pop("rpy_rad"), "missing key(s) base_to_gls.rpy_rad"),
])
def test_malformed_files_are_refused(edit, message):
    document = copy.deepcopy(_document())
    edit(document)
    if message is None:       # 40 m is a strange but possible cell: accepted
        cell_frames_from_dict(document)
        return
    with pytest.raises(ValueError) as error:
        cell_frames_from_dict(document)
    assert str(error.value).startswith(message)


def test_unreadable_file_names_itself(tmp_path):
    path = tmp_path / "cell.yaml"
    path.write_text("frames: [\n")
    with pytest.raises(ValueError, match=f"cannot parse cell frames file {path}"):
        load_cell_frames(path)
    path.write_text("- 1\n")
    with pytest.raises(ValueError, match=f"{path}: the cell frames file must be a mapping"):
        load_cell_frames(path)
