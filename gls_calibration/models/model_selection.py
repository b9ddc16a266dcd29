"""Choosing a deviation model: cross-validation and the grid search of its parameters.

Choosing a deviation model: cross-validation (folds, spatially blocked when points are given) and
the grid search over the RBF spread and the spline's smoothing.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Optional, Protocol

import numpy as np

from gls_calibration.common.validation import (as_integer_at_least, as_matching_points, as_non_negative_number,
                                               as_positive_number)
from gls_calibration.models.ols_rbf import OLSRBFNetwork, forward_selection, stop_count
from gls_calibration.models.thin_plate_spline import ThinPlateSplineModel


class DeviationModel(Protocol):
    """What the correction needs from a model: a callable from points (mm) to deviations (mm)."""

    def __call__(self, points) -> np.ndarray:
        """Return the deviations at ``points``.

        Parameters
        ----------
        points : array_like, shape (n, 2)
            Where to evaluate, mm.

        Returns
        -------
        numpy.ndarray, shape (n, 2)
            The deviations, mm.
        """

    def to_dict(self) -> dict:
        """Plain form of the model for the calibration file."""


@dataclass(frozen=True)
class CrossValidation:
    """K-fold cross-validation: RMS Euclidean held-out residual, per fold and overall (mm)."""

    rms_mm: float
    fold_rms_mm: tuple[float, ...]
    residuals: np.ndarray        # (N, 2) held-out residual Y - prediction, in input order


def _fold_indices(count: int, folds: int, seed, points: Optional[np.ndarray] = None,
                  block_mm: Optional[float] = None) -> list[np.ndarray]:
    """Seeded folds: points at random, or whole square blocks of ``block_mm`` (spatially blocked).

    When measurement errors are correlated between neighbours, a random split leaves a held-out
    point's correlated neighbours in training, and the CV error favours models that follow the
    measurement error; holding out whole blocks wider than that correlation keeps the CV honest.
    """
    folds = as_integer_at_least(folds, "folds", 2)
    if count < folds:
        raise ValueError(f"cannot split {count} point(s) into {folds} folds")
    rng = np.random.default_rng(seed)
    if block_mm is None:
        return np.array_split(rng.permutation(count), folds)
    block_mm = as_positive_number(block_mm, "block_mm")
    cells = np.floor((points - points.min(axis=0)) / block_mm).astype(np.int64)
    _, block = np.unique(cells, axis=0, return_inverse=True)
    block = block.ravel()
    if block.max() + 1 < folds:
        raise ValueError(f"{block.max() + 1} block(s) of {block_mm:g} mm cannot make {folds} folds")
    sizes = np.zeros(folds, dtype=int)
    members: list[list[int]] = [[] for _ in range(folds)]
    for label in rng.permutation(block.max() + 1):    # each block to the smallest fold so far
        smallest = int(np.argmin(sizes))
        chosen = np.flatnonzero(block == label)
        members[smallest].extend(chosen.tolist())
        sizes[smallest] += chosen.size
    return [np.sort(np.asarray(fold, dtype=int)) for fold in members]


def _summarise(residuals: np.ndarray, split: list[np.ndarray]) -> CrossValidation:
    squared = np.sum(residuals ** 2, axis=1)
    return CrossValidation(float(np.sqrt(squared.mean())),
                           tuple(float(np.sqrt(squared[fold].mean())) for fold in split), residuals)


def cross_validate(make_model: Callable[[np.ndarray, np.ndarray], DeviationModel], X, Y,
                   folds: int = 5, seed=0, block_mm: Optional[float] = None) -> CrossValidation:
    """Cross-validate ``make_model(X_train, Y_train)`` over K folds of a seeded random split.

    K-fold cross-validation of ``make_model(X_train, Y_train)`` on a seeded random split
    (``block_mm``: whole square blocks held out together).
    """
    X, Y = as_matching_points(X, Y, "X", "Y", 2)
    split = _fold_indices(X.shape[0], folds, seed, X, block_mm)
    residuals = np.empty_like(Y)
    for held_out in split:
        training = np.setdiff1d(np.arange(X.shape[0]), held_out)
        model = make_model(X[training], Y[training])
        residuals[held_out] = Y[held_out] - model(X[held_out])
    return _summarise(residuals, split)


@dataclass(frozen=True)
class CandidateScore:
    """One model configuration and its cross-validated error."""

    method: str                   # "ols_rbf" or "thin_plate_spline"
    parameters: Mapping[str, float]
    cv_rms_mm: float
    fold_rms_mm: tuple[float, ...]


@dataclass(frozen=True)
class ModelSelection:
    """Every candidate's cross-validated error and the chosen one (refitted on all data)."""

    candidates: tuple[CandidateScore, ...]
    chosen: CandidateScore
    folds: int
    seed: int

    @property
    def method(self) -> str:
        """Name of the chosen method."""
        return self.chosen.method

    def to_dict(self) -> dict:
        """Plain-number description (YAML-ready)."""
        def entry(score: CandidateScore) -> dict:
            return {"method": score.method, "parameters": dict(score.parameters),
                    "cv_rms_mm": score.cv_rms_mm, "fold_rms_mm": list(score.fold_rms_mm)}
        return {"method": self.method, "chosen": entry(self.chosen), "folds": self.folds, "seed": self.seed,
                "candidates": [entry(score) for score in self.candidates]}


def select_model(X, Y, spreads_mm: Sequence[float] = (20.0, 25.0, 30.0, 35.0, 45.0, 60.0),
                 mse_goals_mm2: Sequence[float] = (0.0002, 0.0005, 0.001),
                 tps_smoothings: Sequence[float] = (0.0, 10.0, 100.0, 300.0, 1000.0, 3000.0),
                 folds: int = 5, seed: int = 0,
                 max_neurons: Optional[int] = None,
                 block_mm: Optional[float] = None) -> tuple[DeviationModel, ModelSelection]:
    """Choose among OLS RBF networks (spread x MSE goal) and thin-plate splines by K-fold CV error.

    Every candidate is scored on the same seeded folds; the lowest CV RMS wins and is refitted
    on all data. The greedy OLS path does not depend on the MSE goal (only where it stops), so
    one selection per spread and fold, run to the smallest goal, serves every goal. ``block_mm``
    holds out whole square blocks of that side together (spatially blocked CV, see ``_fold_indices``).
    """
    X, Y = as_matching_points(X, Y, "X", "Y", 2)
    split = _fold_indices(X.shape[0], folds, seed, X, block_mm)
    spreads = [as_positive_number(value, "spreads_mm") for value in spreads_mm]
    goals = sorted(as_non_negative_number(value, "mse_goals_mm2") for value in mse_goals_mm2)
    smoothings = [as_non_negative_number(value, "tps_smoothings") for value in tps_smoothings]
    if max_neurons is not None:
        max_neurons = as_integer_at_least(max_neurons, "max_neurons", 1)
    if not spreads and not smoothings:
        raise ValueError("select_model needs at least one candidate (spreads_mm or tps_smoothings)")
    if spreads and not goals:
        raise ValueError("mse_goals_mm2 must hold at least one value when spreads_mm is given")

    scores: list[CandidateScore] = []
    trainings = [np.setdiff1d(np.arange(X.shape[0]), held_out) for held_out in split]
    for spread in spreads:
        residuals = {goal: np.empty_like(Y) for goal in goals}
        for training, held_out in zip(trainings, split):
            limit = training.size if max_neurons is None else min(max_neurons, training.size)
            order, history = forward_selection(X[training], Y[training], spread, goals[0], limit)
            for goal in goals:
                model = OLSRBFNetwork._from_selection(X[training], Y[training], order[:stop_count(history, goal)],
                                                      spread, goal, max_neurons)
                residuals[goal][held_out] = Y[held_out] - model(X[held_out])
        for goal in goals:
            summary = _summarise(residuals[goal], split)
            scores.append(CandidateScore("ols_rbf", {"spread_mm": spread, "mse_goal_mm2": goal},
                                         summary.rms_mm, summary.fold_rms_mm))
    for smoothing in smoothings:
        summary = cross_validate(lambda x, y: ThinPlateSplineModel(x, y, smoothing), X, Y, folds, seed, block_mm)
        scores.append(CandidateScore("thin_plate_spline", {"smoothing": smoothing},
                                     summary.rms_mm, summary.fold_rms_mm))

    chosen = min(scores, key=lambda score: score.cv_rms_mm)
    if chosen.method == "ols_rbf":
        model: DeviationModel = OLSRBFNetwork(X, Y, chosen.parameters["spread_mm"],
                                              chosen.parameters["mse_goal_mm2"], max_neurons)
    else:
        model = ThinPlateSplineModel(X, Y, chosen.parameters["smoothing"])
    return model, ModelSelection(tuple(scores), chosen, len(split), seed)
