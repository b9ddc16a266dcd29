"""rbf_trainer: serves ``rbf/train``, a deviation model chosen by cross-validation.

With ``physics_first`` the named effects are fitted first (discrepancy workflow) and the RBF/TPS
takes what they leave; the answer is then one ``sum`` model (physics + RBF).
"""
from __future__ import annotations

import numpy as np
import yaml

from gls_calibration import rbf
from gls_calibration.nodes.base import GlsNode, run_node
from gls_calibration.nodes.head_parameters import declare_head_geometry
from gls_calibration.physical_model import train_physics_then_rbf
from gls_calibration.validation import as_matching_points
from gls_calibration_msgs.srv import TrainCorrection


class RbfTrainerNode(GlsNode):
    """Thin wrapper over ``rbf.select_model`` (or ``physical_model.train_physics_then_rbf``)."""

    def __init__(self, **kwargs) -> None:
        super().__init__("rbf_trainer", **kwargs)
        self.spreads_mm = self.declare_numbers("spreads_mm", [25.0, 35.0, 45.0, 60.0],
                                       "Gaussian spreads tried by the grid search (mm)")
        self.mse_goals_mm2 = self.declare_numbers("mse_goals_mm2", [0.0002, 0.0005],
                                          "training MSE goals tried by the grid search (mm^2)")
        self.tps_smoothings = self.declare_numbers("tps_smoothings", [0.0, 10.0, 100.0, 300.0, 1000.0, 3000.0],
                                                   "thin-plate-spline smoothings tried ([] disables the TPS)",
                                                   positive=False, allow_empty=True)
        self.folds = self.declare("folds", 5, "folds of the cross-validation", minimum=2, maximum=50)
        self.seed = self.declare("seed", 0, "seed of the fold assignment", minimum=0)
        self.physics_first = self.declare(
            "physics_first", False,
            "fit the named physical effects first and the RBF on what they leave (needs deviations of a "
            "plate marked through the nominal model)")
        self.max_points = self.declare("max_points", 5000, "most training points of one request",
                                       minimum=3, maximum=100_000)
        self.geometry = declare_head_geometry(self)
        self.create_service(TrainCorrection, "rbf/train", self.on_train)

    def on_train(self, request, response):
        """Train; ``success=false`` with the reason on bad data."""
        try:
            if len(request.x) != len(request.y) or len(request.dx) != len(request.dy):
                raise ValueError("x and y, and dx and dy, must have the same lengths")
            if len(request.x) > self.max_points:
                raise ValueError(f"{len(request.x)} points refused: at most {self.max_points} (parameter "
                                 "max_points; the model selection needs memory growing with its square)")
            landed, corrections = as_matching_points(
                np.column_stack([request.x, request.y]), np.column_stack([request.dx, request.dy]),
                "landed points (x, y)", "corrections (dx, dy)", 2)
            options = dict(spreads_mm=tuple(self.spreads_mm), mse_goals_mm2=tuple(self.mse_goals_mm2),
                           tps_smoothings=tuple(self.tps_smoothings), folds=self.folds, seed=self.seed)
            if self.physics_first:
                # Through the nominal model, the plate was commanded at Q = P + correction.
                model, report = train_physics_then_rbf(landed + corrections, corrections, self.geometry,
                                                       **options)
                residual_model, selection, method = report.residual_model, report.selection, report.method
                named = ", ".join(report.named_effects) or "no effect named"
                message = f"{method} ({named}): CV RMS {selection.chosen.cv_rms_mm:.4f} mm"
            else:
                model, selection = rbf.select_model(landed, corrections, **options)
                residual_model, method = model, selection.method
                message = f"{method}: CV RMS {selection.chosen.cv_rms_mm:.4f} mm"
        except ValueError as error:
            response.success = False
            response.message = str(error)
            return response
        response.success = True
        response.model_yaml = yaml.safe_dump(model.to_dict(), sort_keys=False)
        response.method = method
        response.neurons = int(getattr(residual_model, "neuron_count", len(landed)))
        response.sigma_mm = float(getattr(residual_model, "spread_mm", 0.0))  # a thin-plate spline has none
        response.cv_rms_mm = float(selection.chosen.cv_rms_mm)
        response.message = message
        return response


def main(args=None) -> None:
    """Console script ``gls-rbf-trainer``."""
    run_node(RbfTrainerNode, args)
