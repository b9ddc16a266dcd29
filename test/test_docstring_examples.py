"""The Examples sections of the public stage functions run and print what they say (doctest)."""
import doctest
import importlib

import pytest

MODULES = ("gls_calibration.geometry.kinematics", "gls_calibration.scan.plate_pose",
           "gls_calibration.fiducials.measure", "gls_calibration.registration.rigid",
           "gls_calibration.models.training", "gls_calibration.correction.setpoints")


@pytest.mark.parametrize("name", MODULES)
def test_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, extraglobs={"np": importlib.import_module("numpy")},
                             optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0, f"{name}: no example found"
    assert result.failed == 0, f"{name}: {result.failed} example(s) failed (printed above)"
