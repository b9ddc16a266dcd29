"""Write a seeded measurement CSV of a head with a galvo encoder nonlinearity (outside the library).

    .venv/bin/python examples/encoder_demo.py marks.csv

Truth: Y galvo gain error 3e-3 and the X encoder nonlinearity of ``user_effects.py`` with an
amplitude of 1.5e-4 rad; 0.02 mm noise per axis; the measured frame rotated and shifted.
"""
from __future__ import annotations

import math
from pathlib import Path
import sys

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from user_effects import encoder_nonlinearity_x  # noqa: E402

from gls_calibration.geometry.effect_table import EffectContext  # noqa: E402
from gls_calibration.geometry.kinematics import HeadGeometry, inverse  # noqa: E402
from gls_calibration.geometry.optics import PhysicalHead  # noqa: E402


def main(path: str) -> None:
    """Write the CSV."""
    geometry = HeadGeometry()
    axis = np.linspace(-95.0, 95.0, 19)
    targets = np.column_stack([np.meshgrid(axis, axis)[0].ravel(), np.meshgrid(axis, axis)[1].ravel()])
    joints = inverse(geometry, targets[:, 0], targets[:, 1])
    landed = PhysicalHead(geometry, {"galvo_gain_y": [3e-3]}).land(joints.alpha_x, joints.alpha_y)[:, :2]
    context = EffectContext(geometry, targets, joints.alpha_x, joints.alpha_y, None)
    landed += encoder_nonlinearity_x().deviation(context, np.array([1.5e-4]))
    rng = np.random.default_rng(13)
    landed += rng.normal(0.0, 0.02, landed.shape)
    c, s = math.cos(0.3), math.sin(0.3)
    measured = landed @ np.array([[c, s], [-s, c]]) + np.array([20.0, -7.0])
    Path(path).write_text("x_cmd,y_cmd,x_meas,y_meas\n" + "\n".join(
        f"{q[0]:.6f},{q[1]:.6f},{m[0]:.6f},{m[1]:.6f}" for q, m in zip(targets, measured)) + "\n")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "marks.csv")
