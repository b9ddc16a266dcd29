"""rbf_trainer: serves ``rbf/train``, a correction model trained by ``training.train_correction``.

With ``physics_first`` the named effects are fitted first (discrepancy workflow) and the RBF/TPS
takes what they leave; the answer is then one ``sum`` model (physics + RBF).
"""
from __future__ import annotations

import numpy as np
import yaml

from gls_calibration.nodes.base import GlsNode, answers_errors, run_node
from gls_calibration.nodes.head_parameters import declare_head_geometry
from gls_calibration.training import TrainingOptions, train_correction
from gls_calibration_msgs.srv import TrainCorrection


class RbfTrainerNode(GlsNode):
    """Thin wrapper over ``training.train_correction``."""

    def __init__(self, **kwargs) -> None:
        super().__init__("rbf_trainer", **kwargs)
        defaults = TrainingOptions()
        self.options = TrainingOptions(
            spreads_mm=tuple(self.declare_numbers("spreads_mm", list(defaults.spreads_mm),
                                                  "Gaussian spreads tried by the grid search (mm)")),
            mse_goals_mm2=tuple(self.declare_numbers("mse_goals_mm2", list(defaults.mse_goals_mm2),
                                                     "training MSE goals tried by the grid search (mm^2)")),
            tps_smoothings=tuple(self.declare_numbers("tps_smoothings", list(defaults.tps_smoothings),
                                                      "thin-plate-spline smoothings tried ([] disables the TPS)",
                                                      positive=False, allow_empty=True)),
            folds=self.declare("folds", defaults.folds, "folds of the cross-validation", minimum=2, maximum=50),
            seed=self.declare("seed", defaults.seed, "seed of the fold assignment", minimum=0),
            block_mm=self.declare("cv_block_mm", 0.0,
                                  "side of the square blocks held out together by the cross-validation (mm): "
                                  "honest when measurement errors are correlated between neighbours; 0: points "
                                  "at random", minimum=0.0) or None)
        self.physics_first = self.declare(
            "physics_first", False,
            "fit the named physical effects first and the RBF on what they leave (needs deviations of a "
            "plate marked through the nominal model)")
        self.max_points = self.declare("max_points", 5000, "most training points of one request",
                                       minimum=3, maximum=100_000)
        self.geometry = declare_head_geometry(self)
        self.create_service(TrainCorrection, "rbf/train", self.on_train)

    @answers_errors(ValueError)
    def on_train(self, request, response):
        """Train; ``success=false`` with the reason on bad data."""
        if len(request.x) != len(request.y) or len(request.dx) != len(request.dy):
            raise ValueError("x and y, and dx and dy, must have the same lengths")
        if len(request.x) > self.max_points:
            raise ValueError(f"{len(request.x)} points refused: at most {self.max_points} (parameter "
                             "max_points; the model selection needs memory growing with its square)")
        trained = train_correction(np.column_stack([request.x, request.y]),
                                   np.column_stack([request.dx, request.dy]), self.geometry,
                                   physics_first=self.physics_first, options=self.options)
        response.success = True
        response.model_yaml = yaml.safe_dump(trained.model, sort_keys=False)
        response.method = trained.method
        response.neurons = trained.neurons
        response.spread_mm = trained.spread_mm
        response.cv_rms_mm = trained.cv_rms_mm
        response.message = trained.description
        return response


def main(args=None) -> None:
    """Console script ``gls-rbf-trainer``."""
    run_node(RbfTrainerNode, args)
