"""The Examples sections of the public stage functions run and print what they say (doctest)."""
import doctest
import importlib

import pytest

MODULES = ("gls_calibration.geometry.kinematics", "gls_calibration.geometry.optics",
           "gls_calibration.scan.plate_pose", "gls_calibration.scan.plate_marks", "gls_calibration.scan.sweep",
           "gls_calibration.fiducials.measure", "gls_calibration.fiducials.targets",
           "gls_calibration.registration.rigid", "gls_calibration.registration.sweep_plan",
           "gls_calibration.registration.self_calibration",
           "gls_calibration.discrepancy.selection", "gls_calibration.discrepancy.run_verdict",
           "gls_calibration.models.deviation_models", "gls_calibration.models.ols_rbf",
           "gls_calibration.models.thin_plate_spline", "gls_calibration.models.training",
           "gls_calibration.correction.setpoints", "gls_calibration.correction.uncertainty_grid",
           "gls_calibration.calibration.record", "gls_calibration.calibration.stated_accuracy",
           "gls_calibration.calibration.store",
           "gls_calibration.report.files")


@pytest.mark.parametrize("name", MODULES)
def test_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, extraglobs={"np": importlib.import_module("numpy")},
                             optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0, f"{name}: no example found"
    assert result.failed == 0, f"{name}: {result.failed} example(s) failed (printed above)"
