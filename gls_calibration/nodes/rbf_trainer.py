"""rbf_trainer: serves ``rbf/train``, a correction model trained by ``training.train_correction``.

With ``physics_first`` the named effects are fitted first (discrepancy workflow) and the RBF/TPS
takes what they leave; the answer is then one ``sum`` model (physics + RBF).
"""
from __future__ import annotations

import numpy as np
import yaml

from gls_calibration.models.training import TRAINER_PARAMETERS, train_correction, training_options_from
from gls_calibration.ros.base import GlsNode
from gls_calibration.ros.head_parameters import declare_head_geometry
from gls_calibration.ros.runtime import run_node
from gls_calibration.ros.service_errors import answers_errors
from gls_calibration_msgs.srv import TrainCorrection

# libyaml's emitter when PyYAML has it: the same numbers as safe_dump's text, written several times faster
SAFE_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


class RbfTrainerNode(GlsNode):
    """Thin wrapper over ``training.train_correction``."""

    def __init__(self, **kwargs) -> None:
        super().__init__("rbf_trainer", **kwargs)
        values = self.declare_specs(TRAINER_PARAMETERS)
        self.options = training_options_from(values)
        self.physics_first = values["physics_first"]
        self.max_points = values["max_points"]
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
        response.model_yaml = yaml.dump(trained.model, Dumper=SAFE_DUMPER, sort_keys=False)
        response.method = trained.method
        response.neurons = trained.neurons
        response.spread_mm = trained.spread_mm
        response.cv_rms_mm = trained.cv_rms_mm
        response.message = trained.description
        return response


def main(args=None) -> int:
    """Console script ``gls-rbf-trainer``."""
    return run_node(RbfTrainerNode, args)
