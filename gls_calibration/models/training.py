"""Training a correction from one plate's measurement: RBF/TPS alone, or the named physical effects first.

The calibrate flow hands over the landed points ``P`` (N, 2) and the corrections ``K(Q) - K(P)``
(N, 2) to add there (mm, gls frame; ``Q - P`` when no calibration was active). This module decides
what to train and describes the result in plain numbers, so any cell (the trainer node, a direct
simulation) trains the same way.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Optional, Sequence

from gls_calibration.common.parameter_specs import ParameterSpec
from gls_calibration.common.validation import as_matching_points
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.models import rbf
from gls_calibration.models.physical_model import train_physics_then_rbf


@dataclass(frozen=True)
class TrainedModel:
    """A trained deviation model as plain numbers, with what training reported.

    Parameters
    ----------
    model : dict
        The model's ``to_dict()`` form (``deviation_models.model_from_dict`` rebuilds it).
    method : str
        ``"ols_rbf"``, ``"thin_plate_spline"`` or ``"physics+<either>"``.
    neurons : int
        Units of the RBF part (training points for a thin-plate spline).
    spread_mm : float
        Spread of the RBF part's Gaussian units, mm; 0 for a thin-plate spline.
    cv_rms_mm : float
        Cross-validated RMS of what the data-driven part was trained on, mm.
    description : str, optional
        One line for a log or a service message.
    named_effects : tuple of str, optional
        Physical effects the model holds (physics first).
    """

    model: dict                 # the model's to_dict() form (deviation_models.model_from_dict rebuilds it)
    method: str                 # "ols_rbf", "thin_plate_spline" or "physics+<either>"
    neurons: int                # units of the RBF part (training points for a thin-plate spline)
    spread_mm: float            # spread of the RBF part's Gaussian units (mm); 0 for a thin-plate spline
    cv_rms_mm: float            # cross-validated RMS of what the data-driven part was trained on (mm)
    description: str = ""       # one line for a log or a service message
    named_effects: tuple[str, ...] = ()   # physical effects the model holds (physics first)


@dataclass(frozen=True)
class TrainingOptions:
    """The grid search of the data-driven part (see ``rbf.select_model``).

    Parameters
    ----------
    spreads_mm : sequence of float, default (25, 35, 45, 60)
        Spreads of the RBF network tried, mm.
    mse_goals_mm2 : sequence of float, default (0.0002, 0.0005)
        Training MSE goals of the RBF network tried, mm^2.
    tps_smoothings : sequence of float, default (0, 10, 100, 300, 1000, 3000)
        Smoothings of the thin-plate spline tried, mm^2 ln mm.
    folds : int, default 5
        Cross-validation folds.
    seed : int, default 0
        Seed of the fold assignment.
    block_mm : float, optional
        Side of spatially blocked folds, mm; None: points at random.
    """

    spreads_mm: Sequence[float] = (25.0, 35.0, 45.0, 60.0)
    mse_goals_mm2: Sequence[float] = (0.0002, 0.0005)
    tps_smoothings: Sequence[float] = (0.0, 10.0, 100.0, 300.0, 1000.0, 3000.0)
    folds: int = 5
    seed: int = 0
    block_mm: Optional[float] = None   # spatially blocked folds of this side (None: points at random)

    def select_kwargs(self) -> dict:
        """Keyword arguments of ``rbf.select_model``."""
        return dict(spreads_mm=tuple(self.spreads_mm), mse_goals_mm2=tuple(self.mse_goals_mm2),
                    tps_smoothings=tuple(self.tps_smoothings), folds=self.folds, seed=self.seed,
                    block_mm=self.block_mm)


_DEFAULTS = TrainingOptions()
# The rbf_trainer node's parameters: the node declares them from this table and ``gls-train --config``
# checks a parameter file against it, so both take and refuse the same values.
TRAINER_PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec("spreads_mm", list(_DEFAULTS.spreads_mm), "Gaussian spreads tried by the grid search (mm)",
                  kind="numbers"),
    ParameterSpec("mse_goals_mm2", list(_DEFAULTS.mse_goals_mm2),
                  "training MSE goals tried by the grid search (mm^2)", kind="numbers"),
    ParameterSpec("tps_smoothings", list(_DEFAULTS.tps_smoothings),
                  "thin-plate-spline smoothings tried ([] disables the TPS)", minimum=0.0, kind="numbers",
                  allow_empty=True),
    ParameterSpec("folds", _DEFAULTS.folds, "folds of the cross-validation", minimum=2, maximum=50, kind="integer"),
    ParameterSpec("seed", _DEFAULTS.seed, "seed of the fold assignment", minimum=0, kind="integer"),
    ParameterSpec("cv_block_mm", 0.0, "side of the square blocks held out together by the cross-validation (mm): "
                  "honest when measurement errors are correlated between neighbours; 0: points at random",
                  minimum=0.0),
    ParameterSpec("physics_first", False, "fit the named physical effects first and the RBF on what they leave "
                  "(needs deviations of a plate marked through the nominal model)", kind="flag"),
    ParameterSpec("max_points", 5000, "most training points of one request", minimum=3, maximum=100_000,
                  kind="integer"),
)
GRID_SEARCH_PARAMETERS = ("spreads_mm", "mse_goals_mm2", "tps_smoothings", "folds", "seed", "cv_block_mm")


def training_options_from(values: Mapping[str, Any]) -> TrainingOptions:
    """Return the grid search of checked trainer parameter values.

    Parameters
    ----------
    values : mapping
        Parameter name (as in ``TRAINER_PARAMETERS``) -> checked value; a missing one keeps its
        default, a ``cv_block_mm`` of 0 means points at random.

    Returns
    -------
    TrainingOptions
        The grid search.
    """
    options = {("block_mm" if name == "cv_block_mm" else name): values[name]
               for name in GRID_SEARCH_PARAMETERS if name in values}
    for field in ("spreads_mm", "mse_goals_mm2", "tps_smoothings"):
        if field in options:
            options[field] = tuple(float(value) for value in options[field])
    if "block_mm" in options:
        options["block_mm"] = options["block_mm"] or None     # 0: points at random
    return TrainingOptions(**options)


def train_correction(landed_xy, corrections, geometry: Optional[HeadGeometry] = None, *,
                     physics_first: bool = False, options: TrainingOptions = TrainingOptions()) -> TrainedModel:
    """Train a correction model at the landed points ``landed_xy`` on ``corrections`` (both (N, 2), mm).

    ``physics_first``: the named effects are fitted first (discrepancy workflow, needs a plate
    marked through the nominal model, which was then commanded at ``Q = P + correction``) and the
    RBF/TPS takes what they leave: one ``sum`` model. Otherwise the RBF/TPS alone, chosen by
    cross-validation.

    Parameters
    ----------
    landed_xy : array_like
        Where the marks landed, P (N, 2), mm in the gls frame, after the rigid alignment.
    corrections : array_like
        What to add at P to land there, K(Q) - K(P) (N, 2), mm.
    geometry : HeadGeometry, optional
        The nominal head (physics first only).
    physics_first : bool
        Fit the named physical effects first.
    options : TrainingOptions
        The grid search of the data-driven part.

    Returns
    -------
    TrainedModel
        The model as plain numbers, its method, size and cross-validated RMS.

    Raises
    ------
    ValueError
        Non-finite or mismatched data, too few points, a bad option.

    Examples
    --------
    >>> from gls_calibration.fiducials.targets import grid_targets
    >>> landed = grid_targets(7, 120.0)[:, :2]
    >>> corrections = np.column_stack([1e-5 * landed[:, 0] * landed[:, 1], 0.02 * np.sin(landed[:, 0] / 40.0)])
    >>> trained = train_correction(landed, corrections)
    >>> print(trained.method, trained.neurons, trained.cv_rms_mm < 0.01)
    thin_plate_spline 49 True
    """
    landed, corrections = as_matching_points(landed_xy, corrections, "landed points (x, y)",
                                             "corrections (dx, dy)", 2)
    if physics_first:
        model, report = train_physics_then_rbf(landed + corrections, corrections, geometry,
                                               **options.select_kwargs())
        residual_model, selection, method = report.residual_model, report.selection, report.method
        named_effects = tuple(report.named_effects)
        named = ", ".join(named_effects) or "no effect named"
        description = f"{method} ({named}): CV RMS {selection.chosen.cv_rms_mm:.4f} mm"
    else:
        model, selection = rbf.select_model(landed, corrections, **options.select_kwargs())
        residual_model, method, named_effects = model, selection.method, ()
        description = f"{method}: CV RMS {selection.chosen.cv_rms_mm:.4f} mm"
    return TrainedModel(model=model.to_dict(), method=method,
                        neurons=int(getattr(residual_model, "neuron_count", len(landed))),
                        spread_mm=float(getattr(residual_model, "spread_mm", 0.0)),  # a spline has none
                        cv_rms_mm=float(selection.chosen.cv_rms_mm), description=description,
                        named_effects=named_effects)
