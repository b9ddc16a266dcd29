"""The nodes of ``gls-sim-cell --streaming``: the simulated cell split as a real one is.

A robot with TF and the motion contract, a line scanner streaming profiles and stream_acquisition;
the rest as usual.
"""
from __future__ import annotations

from rclpy.context import Context

from gls_calibration.nodes.calibration_manager import CalibrationManager
from gls_calibration.nodes.correction import CorrectionNode
from gls_calibration.nodes.fiducial_measurement import FiducialMeasurementNode
from gls_calibration.nodes.plate_pose import PlatePoseNode
from gls_calibration.nodes.rbf_trainer import RbfTrainerNode
from gls_calibration.nodes.sim_galvo import SimGalvoNode
from gls_calibration.nodes.sim_line_scanner import SimLineScannerNode
from gls_calibration.nodes.sim_robot import SimRobotNode
from gls_calibration.nodes.stream_acquisition import StreamAcquisitionNode


def streaming_nodes(context: Context, namespace: str) -> list:
    """Every node of the split simulated cell, the manager last (as gls-sim-cell expects)."""
    nodes = [SimGalvoNode(context=context, namespace=namespace)]
    robot = SimRobotNode(context=context, namespace=namespace)
    nodes += [robot, SimLineScannerNode(robot, context=context, namespace=namespace)]
    nodes += [node_type(context=context, namespace=namespace)
              for node_type in (StreamAcquisitionNode, PlatePoseNode, FiducialMeasurementNode, RbfTrainerNode,
                                CorrectionNode, CalibrationManager)]
    return nodes
