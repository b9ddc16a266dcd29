"""One owner for the fiducial design: the radii the cell marks with are the radii it measures with."""
import pytest

from gls_calibration_msgs.srv import Calibrate

CALIBRATE_TIMEOUT_S = 300.0
RADII = [3.0, 3.2]
FAST = {"sweep.plain_repeats": 1, "sweep.plan": "0+"}


@pytest.mark.parametrize("who", ["every node (config/gls.yaml)", "the manager only"])
def test_ring_radii_set_once_reach_the_measurement(start_cell, who):
    """Radii set in gls.yaml (``grid.ring_radii_mm``, read by every node) are measured as marked; and the
    manager's radii travel in every MeasureFiducials request, so a fiducial node left at its default
    2.5 / 2.7 mm still finds every ring (issue 29: one owner)."""
    if who == "the manager only":
        cell = start_cell(grid=3, parameters=FAST,
                          node_parameters={"calibration_manager": {"grid.ring_radii_mm": RADII}})
        assert cell.nodes["fiducial_measurement"].ring_radii_mm == (2.5, 2.7)
    else:
        cell = start_cell(grid=3, parameters={**FAST, "grid.ring_radii_mm": RADII})
        assert cell.nodes["fiducial_measurement"].ring_radii_mm == tuple(RADII)
    answer = cell.call(Calibrate, "calibrate", Calibrate.Request(force=True), CALIBRATE_TIMEOUT_S)
    assert answer.success, answer.message
    assert answer.fiducials_found == answer.fiducials_expected == 9


def test_a_sweep_too_short_for_the_grid_and_its_rings_is_refused_with_the_sizes():
    """A ring cut by the end of a sweep is found or lost by chance: the settings refuse such a sweep."""
    from gls_calibration.calibration.procedure import ProcedureSettings
    from gls_calibration.registration.sweep_plan import CellTimeModel
    with pytest.raises(ValueError) as error:
        ProcedureSettings(ring_radii_mm=tuple(RADII), cell_time=CellTimeModel(sweep_length_mm=200.0))
    assert str(error.value) == ("sweep length 200 mm cannot cover the grid: its 190 mm, the outer ring (3.2 mm) "
                                "and 4 mm at each end need 204.4 mm")
    assert ProcedureSettings(ring_radii_mm=tuple(RADII), cell_time=CellTimeModel(sweep_length_mm=204.4))
    assert ProcedureSettings(ring_radii_mm=tuple(RADII)).cell_time.sweep_length_mm == 210.0    # the default covers them
