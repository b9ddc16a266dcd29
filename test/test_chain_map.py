"""Chain map: the lines' repeating robot error fitted against known centres and removed (issue 32)."""
from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest

from gls_calibration.fiducials.measure import FiducialMeasurement
from gls_calibration.registration.chain_map import (NO_CHAIN_MAP, ChainMap, ChainMapFit, ReferenceSweep,
                                                    chain_map_identity, correct_measurements, fit_chain_map,
                                                    load_chain_map, save_chain_map, travel_direction)
from gls_calibration.registration.sweep_plan import parse_plan
from gls_calibration.scan.plate_pose import estimate_plate_pose

LINES = ("0+", "0-", "90+", "90-")


def travel_axis(line: str) -> int:
    """The B axis (0: x, 1: y) along which an axis-aligned line travels."""
    return int(np.argmax(np.abs(travel_direction(line))))


def true_error(line: str, xy: np.ndarray) -> np.ndarray:
    """A known repeating error per line (B x, y, mm): a travel scale and a smooth along-travel part
    (up to ~0.06 mm), and a smaller smooth cross-track part, different for every line."""
    k = LINES.index(line)
    axis = travel_axis(line)
    u = xy[:, axis]
    along = (1.5e-4 * (k + 1) * (-1) ** k) * u + 0.04 * np.sin(u / 17.0 + k) + 0.015 * np.cos(u / 9.0 - 2 * k)
    across = 0.02 * np.sin(u / 23.0 - k)
    error = np.zeros((len(xy), 2))
    error[:, axis] = along
    error[:, 1 - axis] = across
    return error


def synthetic_sweeps(noise_mm: float, repeats: int = 2, seed: int = 5) -> list[ReferenceSweep]:
    """A 19 x 19 plate at 10 mm (known in its own frame) laid turned and shifted in B, swept along
    every line, each centre measured with the line's error and white noise."""
    rng = np.random.default_rng(seed)
    axis = (np.arange(19) - 9) * 10.0
    known = np.array([(a, b) for b in axis for a in axis])
    angle, shift = 0.004, np.array([1.3, 100.0 - 0.7])
    c, s = math.cos(angle), math.sin(angle)
    placed = known @ np.array([[c, s], [-s, c]]) + shift
    sweeps = []
    for _ in range(repeats):
        for line in LINES:
            measured = placed + true_error(line, placed) + noise_mm * rng.standard_normal(placed.shape)
            sweeps.append(ReferenceSweep(line, 0, known, measured))
    return sweeps


def test_fit_recovers_a_known_field_and_its_scale():
    chain_map = fit_chain_map(synthetic_sweeps(noise_mm=0.003), "synthetic plate")
    assert chain_map.labels == tuple(sorted(LINES))
    # where the plate lies is unknown, so one shift common to every line is not observable: compare
    # after removing the mean difference over all lines (the gauge), and nothing else
    u = np.linspace(-85.0, 85.0, 35)
    points = {line: (np.column_stack([np.zeros_like(u), 100.0 + u]) if travel_axis(line) == 1
                     else np.column_stack([u, np.full_like(u, 100.0)])) for line in LINES}
    difference = {line: chain_map.error_mm(line, points[line]) - true_error(line, points[line]) for line in LINES}
    gauge = np.mean(np.vstack(list(difference.values())), axis=0)
    assert np.all(np.abs(gauge) < 0.05)
    for line in LINES:
        left = difference[line] - gauge
        assert np.sqrt(np.mean(left ** 2)) < 0.004, (line, left)
        # the travel scale (the along slope over the plate) comes back: it is no rigid motion
        along = travel_axis(line)
        fitted = np.polyfit(u, chain_map.error_mm(line, points[line])[:, along], 1)[0]
        wanted = np.polyfit(u, true_error(line, points[line])[:, along], 1)[0]
        assert abs(fitted - wanted) < 2e-5, (line, fitted, wanted)
    assert max(chain_map.residual_rms_mm) < 0.004
    assert chain_map.sweeps_per_line == 2


def test_a_45_deg_line_is_mapped_along_its_diagonal_travel():
    """The 45 deg line's coordinate runs along its travel, (-1, 1) / sqrt(2) in B: an error that is a
    function of it comes back, beside a 0 deg line without error that holds the plate."""
    assert np.allclose(travel_direction("45-"), [-math.sqrt(0.5), math.sqrt(0.5)])
    rng = np.random.default_rng(3)
    axis = (np.arange(19) - 9) * 10.0
    known = np.array([(a, b) for b in axis for a in axis])
    placed = known + np.array([0.0, 100.0])
    direction = travel_direction("45+")

    def error(xy):
        u = (xy - [0.0, 100.0]) @ direction
        across = np.array([direction[1], -direction[0]])
        return np.outer(0.04 * np.sin(u / 19.0) + 2e-4 * u, direction) + np.outer(0.01 * np.cos(u / 13.0), across)

    sweeps = [ReferenceSweep(line, 0, known, placed + (error(placed) if line == "45+" else 0.0)
                             + 0.002 * rng.standard_normal(placed.shape)) for line in ("0+", "45+") for _ in range(2)]
    chain_map = fit_chain_map(sweeps, "synthetic plate")
    u = np.linspace(-85.0, 85.0, 35)
    points = np.array([0.0, 100.0]) + np.outer(u, direction)
    difference = chain_map.error_mm("45+", points) - error(points)
    assert np.sqrt(np.mean(difference ** 2)) < 0.004, difference
    assert np.max(np.abs(chain_map.error_mm("0+", points - np.outer(u, direction) + np.outer(u, [0.0, 1.0])))) < 0.004


def test_no_field_fits_to_noise_only():
    sweeps = synthetic_sweeps(noise_mm=0.003)
    flat = [dataclasses.replace(s, measured_xy_mm=s.measured_xy_mm - true_error(s.line, s.measured_xy_mm))
            for s in sweeps]
    chain_map = fit_chain_map(flat, "synthetic plate")
    u = np.linspace(-85.0, 85.0, 35)
    for line in LINES:
        xy = np.zeros((u.size, 2))
        xy[:, travel_axis(line)] = u + (100.0 if travel_axis(line) == 1 else 0.0)
        xy[:, 1 - travel_axis(line)] = 100.0 if travel_axis(line) == 0 else 0.0
        assert np.max(np.abs(chain_map.error_mm(line, xy))) < 0.003


def test_correcting_removes_the_field_from_another_plate():
    chain_map = fit_chain_map(synthetic_sweeps(noise_mm=0.002), "synthetic plate")
    rng = np.random.default_rng(11)
    other = np.column_stack([rng.uniform(-90, 90, 200), 100.0 + rng.uniform(-90, 90, 200)])
    for line in LINES:
        measured = other + true_error(line, other)
        corrected = chain_map.correct(line, measured)
        before = measured - other
        after = corrected - other
        after -= after.mean(axis=0)     # the gauge: a common shift
        assert np.sqrt(np.mean(after ** 2)) < 0.25 * np.sqrt(np.mean((before - before.mean(axis=0)) ** 2))


def _measurement(centres: np.ndarray) -> FiducialMeasurement:
    plane = np.column_stack([np.random.default_rng(3).uniform(-100, 100, (2000, 2)), np.zeros(2000)])
    pose = estimate_plate_pose(plane)
    n = len(centres)
    return FiducialMeasurement(centres=centres, centres_plane=pose.to_plane(centres), quality=np.full(n, 0.001),
                               radii=np.full(n, 2.7), inner_radii=np.full(n, 2.5), merged=0, rejected=0, missing=0,
                               image_shape=(10, 10), pixel_pitch_mm=(0.1, 0.1)), pose


def test_measurements_are_corrected_per_line_and_unchanged_without_a_map():
    chain_map = fit_chain_map(synthetic_sweeps(noise_mm=0.002), "synthetic plate")
    centres = np.array([[10.0, 40.0, 0.0], [-30.0, 150.0, 0.0]])
    found, pose = _measurement(centres)
    passes = parse_plan("0+,90-")
    assert correct_measurements(None, [found, found], passes, pose)[0] is found
    corrected = correct_measurements(chain_map, [found, found], passes, pose)
    for item, result in zip(passes, corrected):
        expected = centres[:, :2] - chain_map.error_mm(item.label, centres)
        assert np.allclose(result.centres[:, :2], expected)
        assert np.allclose(result.centres[:, 2], centres[:, 2])
        assert np.allclose(result.centres_plane, pose.to_plane(result.centres))
    with pytest.raises(ValueError, match="^chain_map must be a ChainMap or None, got str$"):
        correct_measurements("map.yaml", [found, found], passes, pose)
    with pytest.raises(ValueError, match=r"^the chain map has no line 90- \(it maps 0\+\); measure the map with "
                                         r"the calibration's sweep plan$"):
        only = ChainMap((chain_map.line_map("0+"),), "plate", 1, (0.0, 0.0))
        correct_measurements(only, [found, found], passes, pose)


def test_round_trip_through_the_file(tmp_path):
    chain_map = fit_chain_map(synthetic_sweeps(noise_mm=0.002, repeats=1), "synthetic plate, S/N 1")
    path = tmp_path / "chain_map.yaml"
    save_chain_map(path, chain_map)
    loaded = load_chain_map(path)
    assert loaded.labels == chain_map.labels and loaded.reference == "synthetic plate, S/N 1"
    assert loaded.sweeps_per_line == 1
    xy = np.array([[5.0, 60.0], [-20.0, 120.0]])
    for line in LINES:
        assert np.allclose(loaded.error_mm(line, xy), chain_map.error_mm(line, xy), atol=1e-12)
    assert not list(tmp_path.glob(".chain_map.yaml.*"))    # no temporary file left
    # the identity a check and a calibration record survives the file and changes with the content
    assert loaded.identity == chain_map.identity and re.fullmatch(r"sha256:[0-9a-f]{16}", chain_map.identity)
    other = dataclasses.replace(chain_map, reference="synthetic plate, S/N 2")
    assert other.identity != chain_map.identity
    assert chain_map_identity(None) == NO_CHAIN_MAP and chain_map_identity(chain_map) == chain_map.identity


def _good_file() -> dict:
    return {"chain_map": {"reference": "plate", "sweeps_per_line": 2, "residual_rms_mm": [0.004, 0.005],
                          "lines": [{"line": "0+", "first_knot_mm": -10.0, "knot_spacing_mm": 10.0,
                                     "error_x_mm": [0.0, 0.01, 0.0, -0.01, 0.0],
                                     "error_y_mm": [0.0, 0.02, 0.01, 0.0, 0.0]}]}}


@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(chain_map=[1]), "a chain map file holds one mapping 'chain_map'"),
    (lambda d: d["chain_map"].update(colour="red"), "unknown key(s) chain_map.colour"),
    (lambda d: d["chain_map"].pop("reference"), "missing key(s) chain_map.reference"),
    (lambda d: d["chain_map"].update(reference=" "),
     "chain_map.reference must name the plate with known centres the map was measured on"),
    (lambda d: d["chain_map"].update(sweeps_per_line=0),
     "chain_map.sweeps_per_line must be an integer of at least 1, got 0"),
    (lambda d: d["chain_map"].update(residual_rms_mm=[0.1]),
     "chain_map.residual_rms_mm must be two non-negative finite numbers, got [0.1]"),
    (lambda d: d["chain_map"].update(lines=[]), "chain_map.lines must be a list of one or more line maps"),
    (lambda d: d["chain_map"]["lines"].append(d["chain_map"]["lines"][0]),
     "chain_map.lines maps a line twice: 0+, 0+"),
    (lambda d: d["chain_map"]["lines"][0].update(line="30+"),
     "chain_map line '30+': sweep plan orientation must be 0, 45 or 90 deg, got 30.0"),
    (lambda d: d["chain_map"]["lines"][0].update(line="0+,0-"),
     "chain_map line must be one sweep plan item, got '0+,0-'"),
    (lambda d: d["chain_map"]["lines"][0].update(knot_spacing_mm=0),
     "chain_map line 0+: knot_spacing_mm must be positive, got 0.0"),
    (lambda d: d["chain_map"]["lines"][0].update(first_knot_mm=".nan"),
     "chain_map line 0+: first_knot_mm must be a finite number, got '.nan'"),
    (lambda d: d["chain_map"]["lines"][0].update(error_x_mm=[0.0, 1.0, "a", 0.0]),
     "chain_map.lines[0].error_x_mm must be a list of numbers"),
    (lambda d: d["chain_map"]["lines"][0].update(error_y_mm=[0.0, 0.01, 0.0]),
     "chain_map line 0+: error_y_mm must be a list of 4 to 1000 numbers"),
    (lambda d: d["chain_map"]["lines"][0].update(error_y_mm=[0.0, 9.0, 0.0, 0.0, 0.0]),
     "chain_map line 0+: error_y_mm must hold finite errors within +-5 mm"),
    (lambda d: d["chain_map"]["lines"][0].update(error_y_mm=[0.0, 0.0, 0.0, 0.0]),
     "chain_map line 0+: error_x_mm and error_y_mm must have the same length (5 != 4)"),
    (lambda d: d["chain_map"]["lines"][0].pop("error_x_mm"), "missing key(s) chain_map.lines[0].error_x_mm"),
])
def test_bad_files_are_refused_with_the_key(tmp_path, change, message):
    import yaml
    document = _good_file()
    change(document)
    path = tmp_path / "map.yaml"
    path.write_text(yaml.safe_dump(document))
    with pytest.raises(ValueError) as caught:
        load_chain_map(path)
    assert str(caught.value) == f"{path}: {message}"


def test_a_good_file_loads_and_refuses_points_beyond_its_knots(tmp_path):
    import yaml
    path = tmp_path / "map.yaml"
    path.write_text(yaml.safe_dump(_good_file()))
    chain_map = load_chain_map(path)
    assert np.allclose(chain_map.error_mm("0+", np.array([[0.0, 0.0], [50.0, 10.0]])), [[0.01, 0.02], [0.0, 0.01]])
    with pytest.raises(ValueError, match=r"^chain map of line 0\+ covers -10 to 30 mm along its travel; a centre at "
                                         r"31 mm lies outside \(or is not finite\)$"):
        chain_map.error_mm("0+", np.array([[0.0, 31.0]]))
    with pytest.raises(ValueError, match=r"^cannot parse chain map file "):
        (tmp_path / "broken.yaml").write_text("chain_map: [")
        load_chain_map(tmp_path / "broken.yaml")


def test_bad_fit_inputs_are_refused():
    good = synthetic_sweeps(noise_mm=0.002, repeats=1)
    with pytest.raises(ValueError, match="^a chain map needs one or more reference sweeps$"):
        fit_chain_map([], "plate")
    with pytest.raises(ValueError, match="^chain map reference must name the plate with known centres$"):
        fit_chain_map(good, "")
    bad = dataclasses.replace(good[0], measured_xy_mm=good[0].measured_xy_mm[:-1])
    with pytest.raises(ValueError, match=r"^reference sweep 0: known_xy_mm \(M, 2\) and measured_xy_mm \(M, 2\+\) "
                                         r"must pair up, got \(361, 2\) and \(360, 2\)$"):
        fit_chain_map([bad], "plate")
    nan = good[1].measured_xy_mm.copy()
    nan[3, 0] = np.nan
    with pytest.raises(ValueError, match="^reference sweep 1: centres must be finite$"):
        fit_chain_map([good[0], dataclasses.replace(good[1], measured_xy_mm=nan)], "plate")
    with pytest.raises(ValueError, match=r"^reference sweep 0: line must be one sweep plan item such as 0\+, "
                                         r"got '30\+'$"):
        fit_chain_map([dataclasses.replace(good[0], line="30+")], "plate")
    with pytest.raises(ValueError, match="^reference sweep 0: plate must be a non-negative integer, got -1$"):
        fit_chain_map([dataclasses.replace(good[0], plate=-1)], "plate")
    with pytest.raises(ValueError, match="^chain map fit knot_spacing_mm must be a positive finite number, got 0$"):
        ChainMapFit(knot_spacing_mm=0)
    with pytest.raises(ValueError, match=r"^centres must have shape \(N, 2\) or \(N, 3\), got \(2, 4\)$"):
        fit_chain_map(good, "plate").correct("0+", np.zeros((2, 4)))
    with pytest.raises(ValueError, match="^save_chain_map needs a ChainMap, got dict$"):
        save_chain_map("/tmp/never_written.yaml", {})


def test_procedure_settings_carry_the_map_into_the_combination():
    """combined_centres_gls removes the map from every sweep before combining (the hook)."""
    from gls_calibration.calibration.procedure import ProcedureSettings, combined_centres_gls
    from gls_calibration.registration.sweep_plan import combine_sweeps

    chain_map = fit_chain_map(synthetic_sweeps(noise_mm=0.002, repeats=1), "synthetic plate")
    axis = (np.arange(5) - 2) * 30.0
    grid = np.array([(a, 100.0 + b, 0.0) for b in axis for a in axis])
    passes = parse_plan("0+,90+")
    found = []
    for item in passes:
        measured = grid.copy()
        measured[:, :2] += true_error(item.label, grid)
        found.append(_measurement(measured))
    pose = found[0][1]
    measurements = [f for f, _ in found]
    with_map = ProcedureSettings(grid_per_side=5, sweep_plan=passes, chain_map=chain_map)
    centres, _ = combined_centres_gls(measurements, with_map, grid, pose)
    corrected = correct_measurements(chain_map, measurements, passes, pose)
    expected = combine_sweeps(corrected, passes, grid, with_map.scanner_to_gls, True,
                              sweep_length_mm=with_map.cell_time.sweep_length_mm)
    assert np.allclose(centres[:, :2], expected.centres_xy)
    plain, _ = combined_centres_gls(measurements, dataclasses.replace(with_map, chain_map=None), grid, pose)
    assert not np.allclose(plain[:, :2], centres[:, :2], atol=1e-3)


def _true_line_error(scanner, item, u: np.ndarray, length_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Where the sensor is (B x-y) at travel positions ``u`` of line ``item`` and the simulated
    robot's repeating error there as the marks see it (measured minus true, B x-y, mm)."""
    start = scanner.start_pose(length_mm, item.direction, item.orientation_deg)
    # the reported travel at which the sensor passes u: where = start + direction * reported * (sensor y in B)
    position = np.zeros((u.size, 3))
    position[:, travel_axis(item.label)] = u
    reported = item.direction * ((position - start[:3, 3]) @ start[:3, 1])
    where = (start[:3, 3] + np.outer(item.direction * reported, start[:3, 1]))[:, :2]
    d, o = item.direction, item.orientation_deg
    along = scanner._robot_field(3, d, o) * reported + scanner._robot_field(0, d, o)(where)
    across = scanner._robot_field(1, d, o)(where)
    moved = np.column_stack([across, d * along, np.zeros_like(along)]) @ start[:3, :3].T
    return where, -moved[:, :2]


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_simulated_map_finds_the_robots_repeating_error_and_nothing_without_it():
    """On the simulated cell, the map measured on the certified plate along the calibration's lines
    recovers the robot's repeating along-travel error (the part the separation trusts), up to the
    one common shift no plate pose tells apart; with the robot's repeating errors off its
    along-travel part is near zero. (The TRUE error after calibration: bench_honest_robot.py --chain-map.)"""
    from gls_calibration.simulation.reference_plate import calibration_plan, measure_chain_map
    from gls_calibration.simulation.world import load_sim_config

    plan = calibration_plan()
    config = dataclasses.replace(load_sim_config(preset="paper_like"), seed=1)
    chain_map = measure_chain_map(config, plan, seed=1, repeats=2)
    assert set(chain_map.labels) == {item.label for item in plan.passes}
    scanner = config.make_scanner()
    u = np.linspace(-85.0, 85.0, 69)    # within the plate (+-90 mm about the field's centre)
    # Along each line's own travel (a 45 deg line's along-travel error has an x and a y part), pooled
    # per travel direction: the lines of one direction share the common shift.
    errors, truths = {}, {}
    for item in plan.passes:
        axis = travel_axis(item.label)
        where, truth = _true_line_error(scanner, item, u + (100.0 if axis == 1 else 0.0), config.sweep_length_mm)
        fitted = chain_map.error_mm(item.label, where)
        direction = travel_direction(item.label)
        errors.setdefault(tuple(direction), []).append((fitted - truth) @ direction)
        truths.setdefault(tuple(direction), []).append(truth @ direction)
    left, size = [], []
    for key in errors:
        difference = np.concatenate(errors[key])
        left.append(difference - difference.mean())           # the common shift along this direction
        size.append(np.concatenate(truths[key]) - np.concatenate(truths[key]).mean())
    left_rms, size_rms = (float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for v in (left, size))
    assert size_rms > 0.02          # the preset's repeating error is there to be found
    assert left_rms < 0.6 * size_rms, (left_rms, size_rms)

    off = dataclasses.replace(config, measurement=dataclasses.replace(
        config.measurement, robot_scale_error=0.0, robot_along_error_mm=0.0, robot_path_error_mm=0.0,
        robot_along_wander_mm=0.0))
    quiet = measure_chain_map(off, plan, seed=1, repeats=1)
    for line in quiet.lines:
        direction = travel_direction(line.line)
        along = np.column_stack([line.error_x_mm, line.error_y_mm]) @ direction
        # knots within the plate: +-90 mm about the field's centre (B x 0, y 100) along the travel
        inside = np.abs(line.knots_mm - np.array([0.0, 100.0]) @ direction) <= 90.0
        assert np.sqrt(np.mean((along[inside] - along[inside].mean()) ** 2)) < 0.01, (line.line, along)
