"""Grid-plate self-calibration (registration/self_calibration.py) against two independent error models.

Model A is the simulator's own Gaussian random field (``measurement.smooth_field``), model B one of
this file (low-order polynomial plus sinusoids); both get a per-pass scale and shear (the robot's
scale per line), a constant and a rotation, and white noise per axis. The solver must recover the
marks to within the noise it propagates itself (``mark_sigma_mm``), beyond the terms it reports as
unobservable; the symmetric linear part comes from a "reference" (here: the truth of the views' mean
linear error, what a certified plate measures in a cell).
"""
import numpy as np
import pytest

from gls_calibration.registration.self_calibration import (GridView, affine_basis, non_affine_part,
                                                           self_calibrate)
from gls_calibration.simulation.measurement import PRESET_CHAINS, smooth_field
from gls_calibration.simulation.plate import Plate
from gls_calibration.simulation.scanner import LaserLineScanner

PITCH = 10.0
SIDE = 11
NODES = np.array([(i, j) for j in range(SIDE) for i in range(SIDE)])
POSITION = PITCH * (NODES - NODES.mean(axis=0))
DESIGN = {"0+": ((0, 0), (0, 1), (1, 0)), "90+": ((0, 0), (1, 0), (0, 1))}
SIGMA = {"0+": (0.003, 0.001), "90+": (0.001, 0.003)}    # cross-track noisier than along-track


def model_a(rng, name):
    """The simulator's random field, 0.05 mm at 20 mm, one per component, plus a linear part."""
    fields = [smooth_field(rng, 0.05, 20.0) for _ in range(2)]
    linear = rng.normal(0.0, 2e-4, (2, 2))

    def error(nodes):
        xy = PITCH * (np.asarray(nodes, float) - NODES.mean(axis=0))
        return np.column_stack([fields[0](xy), fields[1](xy)]) + xy @ linear.T + 0.01
    return error


def model_b(rng, name):
    """An independent model: a low-order polynomial and a few sinusoids, plus a linear part."""
    quad = rng.normal(0.0, 0.02, (2, 3))
    waves = [(rng.normal(0.0, 0.02), rng.uniform(15.0, 60.0), rng.uniform(0, 2 * np.pi), rng.uniform(0, np.pi))
             for _ in range(4)]
    linear = rng.normal(0.0, 2e-4, (2, 2))

    def error(nodes):
        xy = PITCH * (np.asarray(nodes, float) - NODES.mean(axis=0))
        u, v = xy[:, 0] / 50.0, xy[:, 1] / 50.0
        out = np.column_stack([quad[c, 0] * u * u + quad[c, 1] * u * v + quad[c, 2] * v * v for c in (0, 1)])
        for index, (size, wavelength, phase, angle) in enumerate(waves):
            along = xy @ np.array([np.cos(angle), np.sin(angle)])
            out[:, index % 2] += size * np.sin(2 * np.pi * along / wavelength + phase)
        return out + xy @ linear.T - 0.02
    return error


def make_views(model, seed, design=DESIGN, rotation_rad=2e-4, noise=True):
    """Truth marks and the views of them through ``model``'s field per pass type."""
    rng = np.random.default_rng(seed)
    truth = POSITION + rng.normal(0.0, 0.5, POSITION.shape)     # marks off their nodes, as a galvo lands them
    fields = {name: model(rng, name) for name in design}
    views = []
    for name, shifts in design.items():
        for shift in shifts:
            angle = rng.normal(0.0, rotation_rad)
            turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
            seen_xy = (truth + fields[name](NODES - np.array(shift))) @ turn.T + rng.normal(0.0, 0.05, 2)
            if noise:
                seen_xy = seen_xy + rng.standard_normal(seen_xy.shape) * np.array(SIGMA[name])
            views.append(GridView(seen_xy, np.ones(len(NODES), bool), shift, name, SIGMA[name]))
    return truth, views


def chain_linear_in_mean(truth, views):
    """The chain's symmetric linear error in the views' mean: what a reference plate measures."""
    mean = np.mean([view.centres_mm for view in views], axis=0)
    coefficients = np.linalg.lstsq(affine_basis(NODES, PITCH), (mean - truth).ravel(), rcond=None)[0]
    return np.array([[coefficients[3], coefficients[5]], [coefficients[5], coefficients[4]]])


def rigid_part_removed(error):
    """``error`` (N, 2) less its best rigid motion (translation, rotation): what a TRUE figure keeps."""
    basis = affine_basis(NODES, PITCH)[:, :3]
    values = error.ravel()
    return (values - basis @ np.linalg.lstsq(basis, values, rcond=None)[0]).reshape(-1, 2)


def within_noise(error, sigma):
    """The check: RMS error within 0.6-1.6x the propagated RMS (enough for the ~240 values here)."""
    ratio = np.sqrt(np.mean(error ** 2)) / np.sqrt(np.mean(sigma ** 2))
    return 0.6 < ratio < 1.6, ratio


@pytest.mark.parametrize("model", [model_a, model_b])
@pytest.mark.parametrize("seed", [1, 2])
def test_marks_recovered_within_the_propagated_noise(model, seed):
    truth, views = make_views(model, seed)
    result = self_calibrate(NODES, views, PITCH, linear_correction=chain_linear_in_mean(truth, views),
                            covariance=True)
    # with the reference's linear part only a rigid motion is left out: the TRUE figure's
    ok, ratio = within_noise(rigid_part_removed(result.marks_mm - truth), result.mark_sigma_mm)
    assert ok, ratio
    raw = np.mean([view.centres_mm for view in views], axis=0)   # the views simply averaged
    assert np.sqrt(np.mean(rigid_part_removed(raw - truth) ** 2)) > 5 * np.sqrt(np.mean(result.mark_sigma_mm ** 2))
    assert max(result.residual_rms_mm) < 2 * max(max(s) for s in SIGMA.values())


@pytest.mark.parametrize("model", [model_a, model_b])
def test_a_wrong_gauge_fails_the_check(model):
    """The same check fails without the reference's linear part, or with it the wrong way round."""
    truth, views = make_views(model, 3)
    linear = chain_linear_in_mean(truth, views)
    for wrong in (None, -linear):
        result = self_calibrate(NODES, views, PITCH, linear_correction=wrong, covariance=True)
        ok, ratio = within_noise(rigid_part_removed(result.marks_mm - truth), result.mark_sigma_mm)
        assert not ok and ratio > 3.0, ratio
        # what is left is the unobservable symmetric linear part: beyond it the marks are right
        ok, _ = within_noise(non_affine_part(result.marks_mm - truth, NODES, PITCH), result.mark_sigma_mm)
        assert ok


def test_noise_free_views_fit_exactly():
    """Exact without rotations; a view rotated by theta leaves theta times a mark's offset from its node."""
    truth, views = make_views(model_b, 4, noise=False, rotation_rad=0.0)
    result = self_calibrate(NODES, views, PITCH, linear_correction=chain_linear_in_mean(truth, views))
    assert max(result.residual_rms_mm) < 1e-8
    assert np.max(np.abs(rigid_part_removed(result.marks_mm - truth))) < 1e-8


def test_unobservable_terms_change_nothing_and_the_rest_does():
    """An affine map of the marks, taken back by every field, leaves the result as it was; a quadratic does not."""
    truth, views = make_views(model_a, 5, noise=False, rotation_rad=0.0)
    base = self_calibrate(NODES, views, PITCH)
    assert base.unobservable[-1].startswith("symmetric linear part")
    basis = affine_basis(NODES, PITCH)
    for column in range(6):
        mode = 1e-3 * basis[:, column].reshape(-1, 2) / np.max(np.abs(basis[:, column]))
        moved = [GridView(view.centres_mm + mode - (mode_at(mode, NODES - np.array(view.shift))), view.seen,
                          view.shift, view.pass_type, view.sigma_mm) for view in views]
        again = self_calibrate(NODES, moved, PITCH)
        assert np.max(np.abs(non_affine_part(again.marks_mm - base.marks_mm, NODES, PITCH))) < 1e-9, column
    bowl = 0.01 * (POSITION / 50.0) ** 2
    moved = [GridView(view.centres_mm + bowl, view.seen, view.shift, view.pass_type, view.sigma_mm) for view in views]
    again = self_calibrate(NODES, moved, PITCH)
    seen = non_affine_part(again.marks_mm - base.marks_mm, NODES, PITCH)
    assert np.max(np.abs(seen - non_affine_part(bowl, NODES, PITCH))) < 1e-8


def mode_at(mode, nodes):
    """An affine mode (given at NODES) evaluated at other nodes: the field's compensating change."""
    coefficients = np.linalg.lstsq(affine_basis(NODES, PITCH), mode.ravel(), rcond=None)[0]
    xy = PITCH * (np.asarray(nodes, float) - NODES.mean(axis=0))
    x, y = xy[:, 0], xy[:, 1]
    tx, ty, rot, sx, sy, shear = coefficients
    # only the symmetric linear part is traded with the fields; translation and rotation are rigid
    return np.column_stack([sx * x + shear * y, shear * x + sy * y])


def test_marks_a_view_missed_are_taken_from_the_others():
    truth, views = make_views(model_b, 6)
    seen = np.ones(len(NODES), bool)
    seen[:SIDE] = False                    # the first row out of this view's reach
    views[1] = GridView(views[1].centres_mm, seen, views[1].shift, views[1].pass_type, views[1].sigma_mm)
    result = self_calibrate(NODES, views, PITCH, linear_correction=chain_linear_in_mean(truth, views),
                            covariance=True)
    ok, ratio = within_noise(rigid_part_removed(result.marks_mm - truth), result.mark_sigma_mm)
    assert ok, ratio


def _views():
    return make_views(model_b, 7)[1]


def _replace(index, **changes):
    views = _views()
    view = views[index]
    values = dict(centres_mm=view.centres_mm, seen=view.seen, shift=view.shift, pass_type=view.pass_type,
                  sigma_mm=view.sigma_mm)
    values.update(changes)
    views[index] = GridView(**values)
    return views


def _nan_centres():
    views = _views()
    centres = views[2].centres_mm.copy()
    centres[4, 1] = np.nan
    return _replace(2, centres_mm=centres)


def _far_shift():
    views = _views()
    far = GridView(views[2].centres_mm, views[2].seen, (40, 0), "0+", views[2].sigma_mm)
    return views[:2] + [far] + views[3:]


def _lonely_mark():
    views = _views()
    out = []
    for number, view in enumerate(views):
        seen = view.seen.copy()
        if number:
            seen[5] = False
        out.append(GridView(view.centres_mm, seen, view.shift, view.pass_type, view.sigma_mm))
    return out


BAD = [
    (lambda: (NODES.astype(float), _views(), PITCH), "nodes must be an (N, 2) array of integer grid indices, "
     "got shape (121, 2) of float64"),
    (lambda: (np.vstack([NODES[:-1], NODES[:1]]), _views(), PITCH),
     "nodes must be distinct; node (0, 0) appears twice"),
    (lambda: (NODES, _views(), 0.0), "pitch_mm must be a positive finite number, got 0.0"),
    (lambda: (NODES, _views(), float("nan")), "pitch_mm must be a positive finite number, got nan"),
    (lambda: (NODES, _views()[:1], PITCH), "self-calibration needs at least 2 views, got 1"),
    (lambda: (NODES, _replace(1, centres_mm=np.zeros((120, 2))), PITCH),
     "view 1: centres_mm must have shape (N, 2) = (121, 2), got (120, 2)"),
    (lambda: (NODES, _nan_centres(), PITCH), "view 2: centres_mm holds non-finite values for seen marks"),
    (lambda: (NODES, _replace(0, seen=np.ones(121)), PITCH), "view 0: seen must be a boolean array of shape (121,)"),
    (lambda: (NODES, _replace(3, shift=(0.5, 0)), PITCH),
     "view 3: shift must be two integers (grid pitches), got (0.5, 0)"),
    (lambda: (NODES, _replace(4, sigma_mm=(0.001, 0.0)), PITCH),
     "view 4: sigma_mm must be two positive finite numbers, got (0.001, 0.0)"),
    (lambda: (NODES, _replace(5, pass_type=""), PITCH), "view 5: pass_type must be a non-empty string, got ''"),
    (lambda: (NODES, _replace(0, seen=np.arange(121) < 2), PITCH), "view 0: sees 2 marks; at least 3 are needed"),
    (lambda: (NODES, _lonely_mark(), PITCH), "mark 5 (node (5, 0)) is seen in 1 view(s); at least 2 are needed"),
    (lambda: (NODES, _far_shift(), PITCH),
     "view 2 (pass '0+', shift (40, 0)) shares 0 field node(s) with the other views of its pass type; at least 3 "
     "are needed (shifts that leave no overlap separate nothing)"),
    (lambda: (NODES, [v for v in _views() if v.shift in ((0, 0), (0, 1))],
              PITCH), "the shifts within the pass types span one direction only; the marks are then unobservable "
     "along the other: give shifts in x and in y"),
    (lambda: (NODES, [v for v in _views() if v.shift == (0, 0) or v.pass_type == "0+"], PITCH),
     "pass type '90+' has views at 1 shift; each pass type needs views at 2 or more shifts (one shift measures its "
     "field and the marks only together)"),
]


@pytest.mark.parametrize("make, message", BAD)
def test_bad_input_is_named(make, message):
    nodes, views, pitch = make()
    with pytest.raises(ValueError) as caught:
        self_calibrate(nodes, views, pitch)
    assert str(caught.value) == message


def test_bad_linear_correction_is_named():
    with pytest.raises(ValueError) as caught:
        self_calibrate(NODES, _views(), PITCH, linear_correction=[[0.0, 1e-4], [0.0, 0.0]])
    assert str(caught.value) == "linear_correction must be a finite symmetric 2x2 matrix (mm per mm)"


def test_simulated_line_offset_default_is_unchanged_and_the_field_follows_the_arm():
    """The sweep's line offset: none is bit-identical; a moved plate keeps the arm's error where the arm runs."""
    chain = PRESET_CHAINS["paper_like"]
    scanner = LaserLineScanner(chain=chain, robot_seed=3)
    plate = Plate(seed=1, chain=chain)
    plain = scanner.sweep_data(plate, 200.0, step_mm=1.0, seed=5)
    zero = scanner.sweep_data(plate, 200.0, step_mm=1.0, seed=5, line_offset_mm=(0.0, 0.0))
    assert np.array_equal(plain.reported_poses, zero.reported_poses)
    assert np.array_equal(plain.xyz, zero.xyz, equal_nan=True)
    shifted = scanner._placement(5, 201, 1.0, scanner._shifted_start(200.0, 1, 0.0, np.array([10.0, 0.0])))
    moved = scanner._placement(5, 201, 1.0, scanner._shifted_start(200.0, 1, 0.0, np.array([10.0, 0.0])),
                               field_shift_mm=np.array([10.0, 0.0]))
    base = scanner._placement(5, 201, 1.0)
    assert np.array_equal(moved[1], base[1]) and not np.allclose(shifted[1], base[1], atol=1e-3)
    with pytest.raises(ValueError, match="plate_moved needs line_offset_mm"):
        scanner.sweep_data(plate, 200.0, step_mm=1.0, plate_moved=True)


def test_separable_field_recovers_a_separable_chain_and_names_a_bad_model():
    """A field that is a function of the column plus one of the row: the separable model fits it exactly."""
    rng = np.random.default_rng(8)
    truth = POSITION + rng.normal(0.0, 0.5, POSITION.shape)
    views = []
    for name, shifts in DESIGN.items():
        column, row = rng.normal(0.0, 0.03, (40, 2)), rng.normal(0.0, 0.03, (40, 2))
        for shift in shifts:
            at = NODES - np.array(shift) + 20
            views.append(GridView(truth + column[at[:, 0]] + row[at[:, 1]], np.ones(len(NODES), bool), shift,
                                  name, SIGMA[name]))
    result = self_calibrate(NODES, views, PITCH, field_model="separable",
                            linear_correction=chain_linear_in_mean(truth, views))
    assert np.max(np.abs(rigid_part_removed(result.marks_mm - truth))) < 1e-8
    with pytest.raises(ValueError) as caught:
        self_calibrate(NODES, views, PITCH, field_model="spline")
    assert str(caught.value) == "field_model must be one of nodes, separable, got 'spline'"
