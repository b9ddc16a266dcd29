"""The marked plate's sweeps are measured while the next one is scanned (``procedure.measure_marked_plate``).

A scripted cell logs when each step begins and ends: with a cell that runs steps side by side
(``start`` schedules a task) the measurement of sweep k overlaps the acquisition of sweep k + 1; with a
cell that runs them when awaited (``start`` returns the step, as ``CoreCell``) the order is strictly
sequential. Both give the same measurements in plan order, and a failure never leaves a measurement
running behind the error.
"""
from __future__ import annotations

import asyncio
from types import SimpleNamespace
import warnings

import numpy as np
import pytest

from gls_calibration.calibration import procedure
from gls_calibration.registration.sweep_plan import parse_plan

PLAN = parse_plan("0+,0-,90+,90-")
EXPECTED = 9
ACQUIRE_S = 0.02
MEASURE_S = 0.06     # longer than an acquisition: a measurement left behind would still be running


class ScriptedCell:
    """acquire_sweep and measure_fiducials that take ``ACQUIRE_S`` and ``MEASURE_S`` and log their begin and end."""

    def __init__(self, *, side_by_side: bool, found=None, failing_sweep=None) -> None:
        self.side_by_side = side_by_side
        self.found = found or {}               # sweep number -> fiducials found (default: all)
        self.failing_sweep = failing_sweep     # this sweep's acquisition raises
        self.log: list[tuple[str, int]] = []
        self.sweeps = 0

    async def acquire_sweep(self, step_mm, direction=1, orientation_deg=0.0):
        number = self.sweeps
        self.sweeps += 1
        self.log.append(("acquire begins", number))
        await asyncio.sleep(ACQUIRE_S)
        if number == self.failing_sweep:
            raise procedure.CalibrationError(f"sweep {number} failed")
        self.log.append(("acquire ends", number))
        return number

    async def measure_fiducials(self, cloud, pose, expected_count, ring_radii_mm):
        self.log.append(("measure begins", cloud))
        await asyncio.sleep(MEASURE_S)
        self.log.append(("measure ends", cloud))
        return SimpleNamespace(sweep=cloud, centres=np.zeros((self.found.get(cloud, expected_count), 3)))

    def start(self, step):
        return asyncio.ensure_future(step) if self.side_by_side else step


def measure(cell: ScriptedCell):
    settings = procedure.ProcedureSettings(sweep_plan=PLAN)
    return asyncio.run(procedure.measure_marked_plate(cell, settings, None, EXPECTED, lambda *_: None))


def at(log, event):
    return log.index(event)


def test_each_sweep_is_measured_while_the_next_is_scanned():
    cell = ScriptedCell(side_by_side=True)
    found = measure(cell)
    assert [item.sweep for item in found] == [0, 1, 2, 3]
    for k in range(len(PLAN) - 1):
        # measurement k begins before acquisition k + 1 ends, and ends after it began
        assert at(cell.log, ("measure begins", k)) < at(cell.log, ("acquire ends", k + 1))
        assert at(cell.log, ("measure ends", k)) > at(cell.log, ("acquire begins", k + 1))


def test_a_cell_that_runs_steps_when_awaited_measures_in_turn():
    cell = ScriptedCell(side_by_side=False)
    found = measure(cell)
    assert [item.sweep for item in found] == [0, 1, 2, 3]
    assert cell.log == [event for k in range(len(PLAN)) for event in
                        ([("acquire begins", k), ("acquire ends", k)] if k == 0 else [])
                        + ([("acquire begins", k + 1), ("acquire ends", k + 1)] if k + 1 < len(PLAN) else [])
                        + [("measure begins", k), ("measure ends", k)]]


@pytest.mark.parametrize("side_by_side", [True, False])
def test_too_few_fiducials_in_one_sweep_fail_the_run_naming_it(side_by_side):
    cell = ScriptedCell(side_by_side=side_by_side, found={1: 5})
    with pytest.raises(procedure.CalibrationError,
                       match=r"^found 5 of 9 fiducials; at least 9 \(90%\) are needed "
                             r"\(sweep 0- of 0\+,0-,90\+,90-\)$"):
        measure(cell)
    assert ("acquire begins", 3) not in cell.log       # the run stops at the next acquisition


def test_a_failed_acquisition_lets_the_running_measurement_end_first():
    cell = ScriptedCell(side_by_side=True, failing_sweep=2)
    with pytest.raises(procedure.CalibrationError, match=r"^sweep 2 failed$"):
        measure(cell)
    assert cell.log[-1] == ("measure ends", 1)          # nothing of the run goes on behind its error


def test_a_failed_acquisition_drops_a_measurement_that_never_began():
    cell = ScriptedCell(side_by_side=False, failing_sweep=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")                   # "coroutine ... was never awaited" would be one
        with pytest.raises(procedure.CalibrationError, match=r"^sweep 2 failed$"):
            measure(cell)
    assert ("measure begins", 1) not in cell.log


def test_a_45_deg_pass_needs_the_share_of_the_fiducials_in_its_view():
    """A 45 deg pass sees the grid's middle band: of the 19 x 19 grid, the 277 inside the grid's square
    turned with it (``sweep_plan.in_view``); 90 % of those (250) are enough for it, 90 % of all for the others."""
    grid = np.stack(np.meshgrid(np.arange(19.0), np.arange(19.0)), -1).reshape(-1, 2) * 10.0 - 90.0
    settings = procedure.ProcedureSettings(sweep_plan=parse_plan("0+,90+,45+"))

    def run(found):
        cell = ScriptedCell(side_by_side=True, found=found)
        return asyncio.run(procedure.measure_marked_plate(cell, settings, None, len(grid), lambda *_: None,
                                                          targets_gls=grid))

    assert [len(item.centres) for item in run({2: 250})] == [361, 361, 250]
    with pytest.raises(procedure.CalibrationError,
                       match=r"^found 249 of the 277 in its view of 361 fiducials; at least 250 \(90%\) are "
                             r"needed \(sweep 45\+ of 0\+,90\+,45\+\)$"):
        run({2: 249})
    with pytest.raises(procedure.CalibrationError, match=r"^found 324 of 361 fiducials; at least 325 \(90%\)"):
        run({1: 324})
