"""Parameters that several nodes declare alike: the head's nominal geometry, the scanner mounting."""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from gls_calibration.geometry.head_config import HEAD_DEFAULTS
from gls_calibration.geometry.kinematics import HeadGeometry
from gls_calibration.registration.rigid import RigidTransform
from gls_calibration.scan.sweep import nominal_mounting
from gls_calibration.ros.base import GlsNode


HEAD_PARAMETERS = ("head.working_distance_mm", "head.mirror_distance_mm", "head.mirror_limit_deg",
                   "head.focus_range_mm")


# (name, default, description, minimum, maximum): the keys of config/head.yaml
HEAD_SPECS = (
    ("head.working_distance_mm", HEAD_DEFAULTS["working_distance_mm"], "X mirror axis to the work plane, d (mm)",
     1.0, None),
    ("head.mirror_distance_mm", HEAD_DEFAULTS["mirror_distance_mm"], "Y mirror axis to X mirror axis, e (mm)",
     0.0, None),
    ("head.mirror_limit_deg", HEAD_DEFAULTS["mirror_limit_deg"], "mechanical mirror limit (deg)", 0.1, 45.0),
    ("head.focus_range_mm", HEAD_DEFAULTS["focus_range_mm"], "focus shift range, +- (mm)", 0.1, None),
)
# the default sweep's mounting (its middle over the gls origin), as config/gls.yaml writes it
SCANNER_TO_GLS_DEFAULTS = dict(zip(("scanner_to_gls.translation_mm", "scanner_to_gls.rpy_rad"), nominal_mounting()))


def declare_head_geometry(node: GlsNode, *, dynamic: bool = False) -> HeadGeometry:
    """Declare ``head.*`` parameters (the keys of config/head.yaml) and return the nominal geometry.

    ``dynamic``: the node applies changes at run time (see GlsNode.apply_parameter_changes).
    """
    values = {name: node.declare(name, default, description, minimum=minimum, maximum=maximum, dynamic=dynamic)
              for name, default, description, minimum, maximum in HEAD_SPECS}
    return head_geometry_from(values)


def head_geometry_from(values: dict) -> HeadGeometry:
    """Return the HeadGeometry of the ``head.*`` parameter values (names as in HEAD_PARAMETERS)."""
    return HeadGeometry(working_distance_mm=values["head.working_distance_mm"],
                        mirror_distance_mm=values["head.mirror_distance_mm"],
                        mirror_limit_rad=math.radians(values["head.mirror_limit_deg"]),
                        focus_range_mm=values["head.focus_range_mm"])


def scanner_to_gls_from(translation_mm, rpy_rad) -> RigidTransform:
    """Return the CAD mounting of the scanner from its parameter values.

    The mounting is sweep start frame -> gls frame; ValueError naming the parameter unless each is 3
    finite numbers.
    """
    checked = []
    for name, value in (("scanner_to_gls.translation_mm", translation_mm), ("scanner_to_gls.rpy_rad", rpy_rad)):
        numbers = None
        if isinstance(value, (list, tuple)) or hasattr(value, "tolist"):
            items = list(value)
            if all(isinstance(item, (int, float)) and not isinstance(item, bool) for item in items):
                numbers = [float(item) for item in items]
        if numbers is None or len(numbers) != 3 or not all(math.isfinite(number) for number in numbers):
            raise ValueError(f"parameter {name}: 3 finite numbers are needed, got {value!r}")
        checked.append(numbers)
    rotation = Rotation.from_euler("xyz", checked[1]).as_matrix()
    return RigidTransform(rotation, np.asarray(checked[0], dtype=float))
