"""Parameters that several nodes declare alike: the head's nominal geometry, the scanner mounting."""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from gls_calibration.head_config import HEAD_DEFAULTS
from gls_calibration.kinematics import HeadGeometry
from gls_calibration.nodes.base import GlsNode
from gls_calibration.registration import RigidTransform


HEAD_PARAMETERS = ("head.working_distance_mm", "head.mirror_distance_mm", "head.mirror_limit_deg",
                   "head.focus_range_mm")


def declare_head_geometry(node: GlsNode, *, dynamic: bool = False) -> HeadGeometry:
    """Declare ``head.*`` parameters (the keys of config/head.yaml) and return the nominal geometry.

    ``dynamic``: the node applies changes at run time (see GlsNode.apply_parameter_changes).
    """
    values = {
        "head.working_distance_mm": node.declare(
            "head.working_distance_mm", HEAD_DEFAULTS["working_distance_mm"],
            "X mirror axis to the work plane, d (mm)", minimum=1.0, dynamic=dynamic),
        "head.mirror_distance_mm": node.declare(
            "head.mirror_distance_mm", HEAD_DEFAULTS["mirror_distance_mm"],
            "Y mirror axis to X mirror axis, e (mm)", minimum=0.0, dynamic=dynamic),
        "head.mirror_limit_deg": node.declare(
            "head.mirror_limit_deg", HEAD_DEFAULTS["mirror_limit_deg"], "mechanical mirror limit (deg)",
            minimum=0.1, maximum=45.0, dynamic=dynamic),
        "head.focus_range_mm": node.declare(
            "head.focus_range_mm", HEAD_DEFAULTS["focus_range_mm"], "focus shift range, +- (mm)",
            minimum=0.1, dynamic=dynamic),
    }
    return head_geometry_from(values)


def head_geometry_from(values: dict) -> HeadGeometry:
    """The HeadGeometry of the ``head.*`` parameter values (names as in HEAD_PARAMETERS)."""
    return HeadGeometry(working_distance_mm=values["head.working_distance_mm"],
                        mirror_distance_mm=values["head.mirror_distance_mm"],
                        mirror_limit_rad=math.radians(values["head.mirror_limit_deg"]),
                        focus_range_mm=values["head.focus_range_mm"])


def declare_scanner_to_gls(node: GlsNode) -> RigidTransform:
    """Declare the CAD mounting of the scanner (sweep start frame -> gls frame) and return it."""
    translation = node.declare("scanner_to_gls.translation_mm", [0.0, 0.0, 325.0],
                               "scanner frame origin in the gls frame at the start of a sweep (mm)")
    rpy = node.declare("scanner_to_gls.rpy_rad", [math.pi, 0.0, 0.0],
                       "scanner frame orientation in the gls frame: roll, pitch, yaw (rad, extrinsic xyz)")
    if len(translation) != 3 or len(rpy) != 3:
        raise ValueError("scanner_to_gls.translation_mm and scanner_to_gls.rpy_rad need 3 numbers each")
    rotation = Rotation.from_euler("xyz", rpy).as_matrix()
    return RigidTransform(rotation, np.asarray(translation, dtype=float))
