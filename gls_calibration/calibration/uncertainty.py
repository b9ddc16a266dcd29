"""The certificate's expanded uncertainty U(x, y) of a corrected target's landing position.

U is a 95 % coverage RADIUS of the 2-D landing position, relative to the best-fit rigid frame of
the field (a rigid motion of the whole field is not observable on one plate). The per-axis
standard uncertainty ``u`` (k = 1) of every contribution below is combined in quadrature (they
are independent sources) and expanded by ``COVERAGE_FACTOR`` = sqrt(-2 ln 0.05) = 2.448: for an
isotropic 2-D Gaussian error of sigma ``u`` per axis, |error| is Rayleigh distributed and stays
within 2.448 u with 95 % probability (k = 2 per axis would cover only 86 %). The stored and served
name stays ``uncertainty_k2_mm`` (the issue's), the factor used is this one.

The budget (all from what the cell knows; no simulation truth):

(a) ``measurement``: each centre's stated standard uncertainty (``PlateRun.sigma_mm``), carried
    through the trained model exactly (``models.linear_response``: the fit is linear in its data);
    a physics-first model through its linearisation at the solution (``physics_response_matrix``,
    x and y coupled: the per-axis figure is the mean of the two axes' variances).
(b) ``chain``: the correlated error of the measurement chain that the sweep plan does not remove and
    the model learns as if it were the head's: from the reference check of the same plan
    (``ChainCheck``), its per-axis sigma with the random part of one centre taken out (the check's
    sigma holds both; the random part is in (a), averaged). Without a matching check nothing
    independent is known: the term is then ASSUMED equal to the chain error the plan's separation
    removed (scanner frame and per-sweep motion; conservative), or, with a plan that separates
    nothing, to one centre's random part, flagged as unsupported (the budget names the basis).
(c) ``model``: the model's error between fiducials from spatially blocked cross-validation: blocks
    of 2x2 and 3x3 fiducials held out give held-out points one and two pitches from the nearest
    training fiducial; their mean squared residual beyond the held-out points' own measurement
    noise, fitted as ``e(d) = e(pitch) (d / pitch)^q`` (q from the two distances, kept within 1..2),
    gives the term at the distance d of every point to its nearest fiducial. Distance rather than
    curvature: what a fiducial pins down is local, and the CV measures the error at known distances
    directly, while a curvature estimate would come from the same noisy model it judges. A
    physics-first model is refitted on the folds with its effects and RBF settings held
    (``physical_model.refit_physics_then_rbf``), as the others keep their hyper-parameters.
(d) ``plate_height``: a plate height error dz scales the landed field by dz / h about the axis
    (h: working distance to the calibration plane): radial error r dz / h, not removed by a rigid
    motion. Once for the calibration's plate and once for the plate a target is used on (measured
    the same way): ``sqrt(2) r sigma_z / h`` radially, ``sigma_z`` the cell's plate-height
    repeatability (``CertificateSettings.plate_height_sigma_mm``).

(e) ``validation`` (only after a validation plate, :func:`with_validation_floor`): the chain term is one
    draw of the check, and the calibration's own draw of the chain's random error is in none of the
    above; the validation plate carries it. Where the validation's RMS in quadrature with the check
    is above the 2-D RMS the budget implies, the difference is added uniformly over the field.

The marking itself (thermal drift of the head over a job, the laser spot) is not in the budget.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
import math
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from gls_calibration.calibration.stated_accuracy import ChainCheck, check_mismatch, placement_name
from gls_calibration.common.validation import as_positive_number
from gls_calibration.correction.uncertainty_grid import COVERAGE_FACTOR, UncertaintyGrid
from gls_calibration.models import rbf
from gls_calibration.models.linear_response import LINEAR_TYPES, physics_response_matrix, response_matrix
from gls_calibration.models.physical_model import physics_first_parts, refit_physics_then_rbf

CONTRIBUTIONS = ("measurement", "chain", "model", "plate_height")
VALIDATION_FLOOR = "validation"
"""The contribution :func:`with_validation_floor` adds when the validation shows more than the budget."""
COVERED_TYPES = LINEAR_TYPES + ("sum",)     # "sum": physics first (``physical_model.train_physics_then_rbf``)
_SAME_POINT_MM = 1e-9     # a model's centre is a training point within this
CHAIN_FROM_CHECK = "reference check"
CHAIN_ASSUMED = "assumed: no reference check of this plan"


@dataclass(frozen=True)
class CertificateSettings:
    """How the U grid is laid and the design values the cell states (mm)."""

    grid_step_mm: float = 2.5           # U map node spacing: fine against the 10.6 mm fiducial pitch
    plate_height_sigma_mm: float = 0.005   # plate height at standstill, k = 1 (20 profiles, ~2000 points each)
    cv_folds: int = 5
    cv_seed: int = 0

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        as_positive_number(self.grid_step_mm, "grid_step_mm")
        as_positive_number(self.plate_height_sigma_mm, "plate_height_sigma_mm")
        if isinstance(self.cv_folds, bool) or not isinstance(self.cv_folds, int) or self.cv_folds < 2:
            raise ValueError(f"cv_folds must be an integer of at least 2, got {self.cv_folds!r}")


@dataclass(frozen=True)
class Contribution:
    """One line of the budget: its per-axis standard uncertainty (k = 1) over the U grid (mm)."""

    name: str
    rms_mm: float
    max_mm: float
    basis: str

    def to_dict(self) -> dict:
        """Return the line as the record's ``uncertainty.budget`` holds it."""
        return {"name": self.name, "rms_mm": self.rms_mm, "max_mm": self.max_mm, "basis": self.basis}


def _field_keys(full_mm: float, central_mm: float, median_mm: float) -> dict:
    """Return the record's keys of U's field figures (``UncertaintyGrid.field_figures``' order)."""
    return {"u95_full_mm": full_mm, "u95_central_150_mm": central_mm, "u95_median_mm": median_mm}


@dataclass(frozen=True)
class TrainingData:
    """One model's training: where, what, how well measured, and the model's dict.

    One model's training: where (landed P, (N, 2) mm), what (corrections (N, 2) mm), how well
    measured (per-axis standard uncertainty of each centre, (N,) mm) and the model's dict.
    """

    landed_xy: np.ndarray
    corrections: np.ndarray
    sigma_mm: np.ndarray
    model: Mapping[str, Any]


@dataclass(frozen=True)
class UncertaintyBudget:
    """The certificate's budget: each contribution, U over the grid and field-wide figures.

    The certificate's budget: each contribution's per-axis standard uncertainty (RMS and max
    over the grid, k = 1), U (95 % radius) over the grid, its field-wide figures, how it was made.
    """

    contributions: tuple[Contribution, ...]
    grid: UncertaintyGrid
    coverage_factor: float
    u95_full_mm: float          # max U over the grid (the calibrated field)
    u95_central_mm: float       # max U over the central 150 x 150 mm
    u95_median_mm: float        # median U over the grid
    model_error_exponent: float   # q of e(d) = e(pitch) (d / pitch)^q
    pitch_mm: float

    def contribution(self, name: str) -> Contribution:
        """Return the contribution called ``name``; KeyError when the budget has none."""
        for item in self.contributions:
            if item.name == name:
                return item
        raise KeyError(name)

    def to_dict(self) -> dict:
        """Return the record's ``uncertainty`` mapping: the grid and the budget (plain numbers)."""
        return {**self.grid.to_dict(),
                "position_relative_to": "best-fit rigid frame of the field",
                **_field_keys(self.u95_full_mm, self.u95_central_mm, self.u95_median_mm),
                "budget": [item.to_dict() for item in self.contributions]}


def uncertainty_budget(trainings: Sequence[TrainingData], region: Mapping[str, float], working_distance_mm: float,
                       check: Optional[ChainCheck], check_matches: bool,
                       settings: CertificateSettings = CertificateSettings(),
                       removed_chain_rms_mm: Optional[float] = None) -> UncertaintyBudget:
    """Return the budget and U grid of a calibration trained on ``trainings`` (one per iteration).

    Parameters
    ----------
    trainings : sequence of TrainingData
        The models the calibration adds and what each was trained on, in order.
    region : mapping
        The calibrated region (``x_min``, ``x_max``, ``y_min``, ``y_max``, ``plane_z_mm``), mm.
    working_distance_mm : float
        The head's d: h = d - plane_z_mm scales the plate-height term.
    check : ChainCheck or None
        The reference check of the chain; ``check_matches`` says it was made with the calibration's
        plan, placement and chain map (``stated_accuracy``'s test); otherwise term (b) is assumed:
        the 2-D RMS of the chain error the sweep plan's separation removed (``removed_chain_rms_mm``,
        scanner frame and per-sweep motion) when given, else one centre's random part (flagged).

    Raises
    ------
    ValueError
        No training data, mismatched shapes, non-finite values, or an empty region.
    """
    if not trainings:
        raise ValueError("uncertainty_budget needs at least one trained model and its training data")
    for training in trainings:
        if training.model.get("type") not in COVERED_TYPES:
            raise ValueError(f"the certificate covers OLS RBF networks, thin-plate splines and physics-first sums "
                             f"trained on the corrections, not a model of type {training.model.get('type')!r}")
    x_min, x_max, y_min, y_max = (float(region[key]) for key in ("x_min", "x_max", "y_min", "y_max"))
    if not (x_max > x_min and y_max > y_min):
        raise ValueError(f"calibrated region is empty: x {x_min:g}..{x_max:g}, y {y_min:g}..{y_max:g} mm")
    height = as_positive_number(float(working_distance_mm) - float(region.get("plane_z_mm", 0.0)),
                                "working distance above the calibration plane")
    x_nodes = _axis(x_min, x_max, settings.grid_step_mm)
    y_nodes = _axis(y_min, y_max, settings.grid_step_mm)
    gx, gy = np.meshgrid(x_nodes, y_nodes)
    points = np.column_stack([gx.ravel(), gy.ravel()])

    measurement_var = np.zeros(len(points))
    random_var = []
    for training in trainings:
        landed, corrections, sigma = _checked(training)
        measurement_var += _measurement_variance(training.model, landed, corrections, sigma, points)
        random_var.append(float(np.mean(sigma ** 2)))
    first = trainings[0]
    landed, corrections, sigma = _checked(first)
    one_centre_var = random_var[0]

    if check is not None and check_matches:
        chain_var = max(0.0, float(np.mean(np.square(check.sigma_mm))) - one_centre_var)
        chain_basis = (f"{CHAIN_FROM_CHECK} ({check.reference}): per-axis {check.sigma_mm[0]:.4f} / "
                       f"{check.sigma_mm[1]:.4f} mm less one centre's random {math.sqrt(one_centre_var):.4f} mm")
    elif removed_chain_rms_mm is not None and math.isfinite(removed_chain_rms_mm) and removed_chain_rms_mm > 0.0:
        # Nothing independent: the error the plan's separation removed stands in for what it may leave
        # (conservative: one centre's random part alone covered 34 % in simulation, careful seed 1)
        chain_var = max(removed_chain_rms_mm ** 2 / 2.0, one_centre_var)
        chain_basis = (f"{CHAIN_ASSUMED}: taken as the chain error the sweep plan removed, "
                       f"{removed_chain_rms_mm:.4f} mm 2-D (conservative)")
    else:
        chain_var = one_centre_var
        chain_basis = (f"{CHAIN_ASSUMED} and no separation: taken equal to one centre's random part "
                       f"{math.sqrt(one_centre_var):.4f} mm (NOT supported: may be far too small)")

    pitch, model_rms_at_pitch, exponent = blocked_cv_model_error(landed, corrections, sigma, first.model, settings)
    from scipy.spatial import cKDTree   # well-kept nearest-neighbour search
    distance = cKDTree(landed).query(points)[0]
    model_2d = model_rms_at_pitch * (distance / pitch) ** exponent
    model_var = model_2d ** 2 / 2.0      # the CV figure is 2-D (|r|); per axis half its square

    radius = np.hypot(points[:, 0], points[:, 1])
    height_radial = math.sqrt(2.0) * radius * settings.plate_height_sigma_mm / height
    height_var = height_radial ** 2 / 2.0    # a radial (1-D) error, shared over the two axes

    total = np.sqrt(measurement_var + chain_var + model_var + height_var)
    u_grid = COVERAGE_FACTOR * total
    contributions = (
        _contribution("measurement", measurement_var,
                      "per-centre sigma through the model (physics first: linearised at its solution)"
                      if any(training.model.get("type") == "sum" for training in trainings)
                      else "per-centre sigma through the model (exact, linear)"),
        _contribution("chain", np.full(len(points), chain_var), chain_basis),
        _contribution("model", model_var, f"blocked CV (2x2, 3x3 fiducials): {model_rms_at_pitch:.4f} mm 2-D at "
                                          f"{pitch:.2f} mm, exponent {exponent:.2f}"),
        _contribution("plate_height", height_var, f"plate height sigma {settings.plate_height_sigma_mm:g} mm, "
                                                  f"twice, over h = {height:.1f} mm"),
    )
    grid = UncertaintyGrid(x_nodes, y_nodes, u_grid.reshape(gx.shape))
    return UncertaintyBudget(contributions, grid, COVERAGE_FACTOR, *grid.field_figures(), float(exponent),
                             float(pitch))


def _validation_floor(grid: UncertaintyGrid, coverage_factor: float, post_rms_mm: float,
                      check: Optional[ChainCheck],
                      check_matches: bool) -> Optional[tuple[UncertaintyGrid, Contribution]]:
    """Return the raised U grid and the budget line of what was added; None: no floor above the budget."""
    post_rms_mm = float(post_rms_mm)
    if post_rms_mm < 0.0:
        raise ValueError(f"post_rms_mm must be non-negative, got {post_rms_mm!r}")
    if check is None or not check_matches or not math.isfinite(post_rms_mm):
        return None
    floor_2d = math.sqrt(post_rms_mm ** 2 + float(np.sum(np.square(check.sigma_mm))))
    per_axis_var = np.square(grid.u_k2_mm / coverage_factor)
    mean_var = float(np.mean(per_axis_var))
    extra = floor_2d ** 2 / 2.0 - mean_var
    if not extra > 0.0:
        return None
    basis = (f"the validation plate's {post_rms_mm:.4f} mm RMS in quadrature with the reference check's "
             f"{check.sigma_mm[0]:.4f} / {check.sigma_mm[1]:.4f} mm: {floor_2d:.4f} mm 2-D, above the budget's "
             f"{math.sqrt(2.0 * mean_var):.4f} mm; the difference added uniformly")
    raised = UncertaintyGrid(grid.x_mm, grid.y_mm, coverage_factor * np.sqrt(per_axis_var + extra))
    return raised, Contribution(VALIDATION_FLOOR, math.sqrt(extra), math.sqrt(extra), basis)


def with_validation_floor(budget: UncertaintyBudget, post_rms_mm: float, check: Optional[ChainCheck],
                          check_matches: bool) -> UncertaintyBudget:
    """Return ``budget`` with U raised, where needed, to what the validation plate and the check show.

    The chain term is one draw of the reference check; the calibration's own draw of the chain's
    random error (the sweeps' random slopes and shapes that the separation leaves in the marks,
    correlated over the plate, so not averaged by the model) is in neither it nor the measurement
    term, and a check that drew low left U below the TRUE error (coverage 0.64-0.71 on one seed of
    five in simulation). The validation plate carries that draw: its measured RMS holds the
    calibration's random draw and the validation's own (the repeating error cancels there), the
    check holds the repeating error and its own draw. Their quadrature sum
    ``sqrt(post_rms^2 + sigma_x^2 + sigma_y^2)`` estimates the 2-D RMS landing error (assuming the
    parts independent; ``stated_accuracy`` states the bound, their plain sum, for the RMS figure).
    Where the 2-D RMS that U implies over the grid (``sqrt(2 mean(u^2))``, u = U / coverage factor,
    per axis) is below it, one uniform per-axis variance is added over the grid to reach it, as the
    contribution ``validation``; otherwise ``budget`` is returned unchanged.

    Parameters
    ----------
    budget : UncertaintyBudget
        The budget made when the calibration was trained (:func:`uncertainty_budget`).
    post_rms_mm : float
        The validation plate's measured 2-D RMS deviation after calibration (``post_rms_mm``).
    check : ChainCheck or None
        The reference check the budget's chain term came from.
    check_matches : bool
        The check was made with the calibration's plan, placement and chain map.

    Returns
    -------
    UncertaintyBudget
        The budget, with the ``validation`` contribution and the raised grid when the floor is above it.

    Raises
    ------
    ValueError
        If ``post_rms_mm`` is negative (NaN or a missing or non-matching check: no floor, unchanged).

    Examples
    --------
    >>> grid = UncertaintyGrid([0.0, 10.0], [0.0, 10.0], [[0.01, 0.01], [0.01, 0.01]])
    >>> budget = UncertaintyBudget((Contribution("chain", 0.004, 0.004, "check"),), grid, COVERAGE_FACTOR,
    ...                            0.01, 0.01, 0.01, 1.0, 10.0)
    >>> check = ChainCheck(sigma_mm=(0.004, 0.004), plan="0+,90+", placement="pose", reference="plate A",
    ...                    centres=143)
    >>> raised = with_validation_floor(budget, 0.012, check, True)
    >>> round(raised.u95_median_mm, 4), raised.contributions[-1].name
    (0.023, 'validation')
    """
    floor = _validation_floor(budget.grid, budget.coverage_factor, post_rms_mm, check, check_matches)
    if floor is None:
        return budget
    grid, line = floor
    full, central, median = grid.field_figures()
    return replace(budget, contributions=budget.contributions + (line,), grid=grid, u95_full_mm=full,
                   u95_central_mm=central, u95_median_mm=median)


def with_validation_floor_stored(stored: Mapping[str, Any], post_rms_mm: float, check: Optional[ChainCheck],
                                 check_matches: bool) -> Optional[dict]:
    """Return a record's ``uncertainty`` mapping raised as :func:`with_validation_floor` does; None: unchanged.

    Parameters
    ----------
    stored : mapping
        The mapping as :meth:`UncertaintyBudget.to_dict` wrote it (a calibration file's ``uncertainty``).
    post_rms_mm, check, check_matches
        As for :func:`with_validation_floor`.

    Returns
    -------
    dict or None
        The raised mapping (grid, field figures, the ``validation`` line appended to ``budget``), or
        None where there is no floor above the budget.

    Raises
    ------
    ValueError
        If ``stored`` holds no valid grid, or ``post_rms_mm`` is negative.
    """
    grid = UncertaintyGrid.from_dict(stored)
    floor = _validation_floor(grid, float(stored.get("coverage_factor", COVERAGE_FACTOR)), post_rms_mm, check,
                              check_matches)
    if floor is None:
        return None
    raised, line = floor
    return {**stored, **raised.to_dict(), **_field_keys(*raised.field_figures()),
            "budget": list(stored.get("budget", [])) + [line.to_dict()]}


def blocked_cv_model_error(landed: np.ndarray, corrections: np.ndarray, sigma: np.ndarray,
                           model: Mapping[str, Any], settings: CertificateSettings) -> tuple[float, float, float]:
    """Return the model's 2-D RMS error one pitch from the nearest fiducial and its growth exponent q.

    The model is refitted with its hyper-parameters on folds of whole 2x2 and 3x3 fiducial blocks;
    each held-out residual's squared length, less the held-out centre's own noise (2 sigma^2), is
    binned by the distance to the nearest training fiducial (one pitch, two pitches). Returns
    (pitch, e(pitch), q).
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(landed)
    pitch = float(np.median(tree.query(landed, k=2)[0][:, 1]))
    make = _refit(model, model.get("type") in LINEAR_TYPES
                  and trained_at(model, landed, corrections) is not landed)
    index = np.rint((landed - landed.min(axis=0)) / pitch).astype(np.int64)
    distances, excess = [], []
    rng = np.random.default_rng(settings.cv_seed)
    for side in (2, 3):
        _, block = np.unique(index // side, axis=0, return_inverse=True)
        block = block.ravel()
        fold_of_block = rng.permutation(block.max() + 1) % settings.cv_folds
        fold = fold_of_block[block]
        for number in range(settings.cv_folds):
            held = fold == number
            if held.all() or np.count_nonzero(~held) < 10:
                continue
            fitted = make(landed[~held], corrections[~held])
            residual = corrections[held] - fitted(landed[held])
            distances.append(cKDTree(landed[~held]).query(landed[held])[0])
            excess.append(np.sum(residual ** 2, axis=1) - 2.0 * sigma[held] ** 2)
    distance = np.concatenate(distances) / pitch
    excess = np.concatenate(excess)
    near = distance < 1.5
    far = (distance >= 1.5) & (distance < 2.5)
    near_ms = max(float(np.mean(excess[near])), 0.0) if near.any() else 0.0
    far_ms = max(float(np.mean(excess[far])), 0.0) if far.any() else 0.0
    centre_near = float(np.mean(distance[near])) if near.any() else 1.0
    centre_far = float(np.mean(distance[far])) if far.any() else 2.0
    if near_ms > 0.0 and far_ms > 0.0:
        exponent = 0.5 * math.log(far_ms / near_ms) / math.log(centre_far / centre_near)
    else:
        exponent = 1.0
    exponent = min(max(exponent, 1.0), 2.0)
    # e at exactly one pitch from the near bin's mean distance
    at_pitch = math.sqrt(near_ms) / centre_near ** exponent
    return pitch, at_pitch, exponent


def _measurement_variance(model: Mapping[str, Any], landed: np.ndarray, corrections: np.ndarray, sigma: np.ndarray,
                          points: np.ndarray) -> np.ndarray:
    """Per-axis variance (M,) of the model at ``points`` from independent per-centre errors ``sigma`` (per axis)."""
    if model.get("type") == "sum":
        # physics first: trained at the targets Q = P + Y on Y, Q fixed (``training.train_correction``)
        response = physics_response_matrix(model, landed + corrections, corrections, points)     # (2M, 2N)
        per_component = (response ** 2) @ np.repeat(sigma ** 2, 2)
        return per_component.reshape(-1, 2).mean(axis=1)
    return (response_matrix(model, trained_at(model, landed, corrections), points) ** 2) @ (sigma ** 2)


def trained_at(model: Mapping[str, Any], landed: np.ndarray, corrections: np.ndarray) -> np.ndarray:
    """Return where a data-driven model was trained: at the landed points P, or at the targets P + Y.

    A physics-first training that named no effect is a plain OLS network or spline trained at the
    targets (``physical_model.train_physics_then_rbf``). Both models' centres are training points
    (all of them for a spline, the chosen ones for an OLS network), so they tell which.

    Parameters
    ----------
    model : mapping
        An ``ols_rbf`` or ``thin_plate_spline`` model's ``to_dict()`` form.
    landed, corrections : numpy.ndarray (N, 2)
        The landed points P and the corrections Y it was trained on, mm.

    Returns
    -------
    numpy.ndarray (N, 2)
        P or P + Y, mm.

    Raises
    ------
    ValueError
        When the model's centres are neither.
    """
    from scipy.spatial import cKDTree

    centres = np.asarray(model.get("centres", ()), dtype=float).reshape(-1, 2)
    if not len(centres):
        return landed       # no unit: the model is its bias, the mean of Y wherever it was trained
    for points in (landed, landed + corrections):
        if float(np.max(cKDTree(points).query(centres)[0])) <= _SAME_POINT_MM:
            return points
    raise ValueError(f"{model.get('type')}: its centres are neither the landed points nor the targets given")


def _refit(model: Mapping[str, Any], at_targets: bool = False):
    """Return a function (X, Y) -> model refitted with ``model``'s hyper-parameters.

    For physics first, X are the landed points P and Y the corrections as ``train_correction`` takes
    them: the model is refitted at the targets P + Y with its effects and its RBF's settings held;
    ``at_targets``: an OLS network or spline trained at the targets P + Y (physics first, no effect named).
    """
    kind = model.get("type")
    if kind == "sum":
        _, residual = physics_first_parts(model)
        residual_refit = _refit(residual)
        return lambda x, y: refit_physics_then_rbf(model, x + y, y, residual_refit)
    if at_targets:
        refit = _refit(model)
        return lambda x, y: refit(x + y, y)
    if kind == "ols_rbf":
        spread, goal, limit = float(model["spread_mm"]), float(model.get("mse_goal_mm2", 0.0)), model.get("max_neurons")
        return lambda x, y: rbf.OLSRBFNetwork(x, y, spread, goal, limit)
    if kind == "thin_plate_spline":
        smoothing = float(model.get("smoothing", 0.0))
        return lambda x, y: rbf.ThinPlateSplineModel(x, y, smoothing)
    raise ValueError(f"model type {kind!r} cannot be refitted for cross-validation")


def _checked(training: TrainingData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    landed = np.asarray(training.landed_xy, dtype=float)
    corrections = np.asarray(training.corrections, dtype=float)
    sigma = np.asarray(training.sigma_mm, dtype=float)
    if landed.ndim != 2 or landed.shape[1] != 2 or corrections.shape != landed.shape or sigma.shape != (len(landed),):
        raise ValueError(f"training data must be landed (N, 2), corrections (N, 2) and sigma (N,), got "
                         f"{landed.shape}, {corrections.shape} and {sigma.shape}")
    if len(landed) < 10:
        raise ValueError(f"training data must hold at least 10 points, got {len(landed)}")
    if not (np.all(np.isfinite(landed)) and np.all(np.isfinite(corrections)) and np.all(np.isfinite(sigma))):
        raise ValueError("training data holds NaN or infinite values")
    if np.any(sigma <= 0.0):
        raise ValueError("sigma_mm must be positive for every centre")
    return landed, corrections, sigma


def _axis(low: float, high: float, step: float) -> np.ndarray:
    return np.linspace(low, high, max(2, int(math.ceil((high - low) / step)) + 1))


def _contribution(name: str, variance: np.ndarray, basis: str) -> Contribution:
    standard = np.sqrt(np.asarray(variance, dtype=float))
    return Contribution(name, float(np.sqrt(np.mean(standard ** 2))), float(standard.max()), basis)


def run_sigma_mm(sigma: Optional[np.ndarray], count: int, floor_mm: float) -> np.ndarray:
    """Per-centre sigma (N,) of a plate run: its stated figures, ``floor_mm`` where none is finite."""
    if sigma is None:
        return np.full(count, floor_mm)
    sigma = np.asarray(sigma, dtype=float)
    return np.where(np.isfinite(sigma) & (sigma > 0.0), sigma, floor_mm)


def check_matches_run(check: Optional[ChainCheck], run: Any, settings: Any) -> bool:
    """Whether the reference ``check`` describes ``run``'s chain (``stated_accuracy.check_mismatch``).

    Parameters
    ----------
    check : ChainCheck or None
        The reference check of the chain.
    run : PlateRun
        A plate of the calibration (its ``sweep_plan``, ``chain_map`` and ``targets``).
    settings : ProcedureSettings
        The run's settings (how profiles were placed).

    Returns
    -------
    bool
        True when plan, placement and chain map match and the check's known centres reach the
        run's targets; False without a check.
    """
    if check is None:
        return False
    return not check_mismatch(check, plan=run.sweep_plan, placement=placement_name(settings.profiles_placed_by_pose),
                              chain_map=run.chain_map, targets_xy_mm=run.targets)


def run_budget(runs: Sequence[Any], models: Sequence[Any], settings: Any, region: Mapping[str, float],
               working_distance_mm: float, check: Optional[ChainCheck],
               certificate: CertificateSettings = CertificateSettings()) -> UncertaintyBudget:
    """Return the uncertainty budget of a calibrate flow's ``runs`` and their trained ``models``.

    The budget of a calibrate flow's ``runs`` (``PlateRun``) and the ``models`` (``TrainedModel``)
    trained on them, with the procedure's ``settings``; the check counts when made with the same
    plan, placement and chain map (as for the stated accuracy).
    """
    if len(runs) != len(models):
        raise ValueError(f"one trained model per plate run is needed, got {len(models)} models for {len(runs)} runs")
    trainings = [TrainingData(run.measured_gls[:, :2], run.corrections,
                              run_sigma_mm(run.sigma_mm, len(run.corrections), settings.measurement_uncertainty_mm),
                              model.model) for run, model in zip(runs, models)]
    matches = check_matches_run(check, runs[0], settings)
    first = runs[0]
    removed = math.hypot(first.scanner_error_rms_mm, first.motion_error_rms_mm)
    return uncertainty_budget(trainings, region, working_distance_mm, check, matches, certificate,
                              removed if math.isfinite(removed) else None)
