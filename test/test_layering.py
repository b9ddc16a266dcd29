"""The core (everything under gls_calibration/ but nodes/ and cli/) never loads rclpy or message packages."""
from __future__ import annotations

import json
from pathlib import Path
import subprocess
import sys

import gls_calibration

PACKAGE = Path(gls_calibration.__file__).parent
ROS_ROOTS = ("rclpy", "rcl_interfaces", "builtin_interfaces", "std_srvs", "rosidl_runtime_py")

PROBE = """
import importlib, json, sys
for name in sys.argv[1:]:
    importlib.import_module(name)
roots = sorted({name.split(".")[0] for name in sys.modules})
print(json.dumps(roots))
"""


def module_names(include_nodes: bool) -> list[str]:
    names = []
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        if not include_nodes and parts[0] in ("nodes", "cli"):
            continue
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names.append(".".join(("gls_calibration",) + parts))
    return names


def loaded_ros_packages(modules: list[str]) -> list[str]:
    """Top-level ROS packages in sys.modules of a fresh interpreter after importing ``modules``."""
    result = subprocess.run([sys.executable, "-c", PROBE, *modules], capture_output=True, text=True, check=True)
    roots = json.loads(result.stdout)
    return [root for root in roots if root in ROS_ROOTS or root.endswith("_msgs")]


def test_core_modules_import_neither_rclpy_nor_messages():
    core = module_names(include_nodes=False)
    assert "gls_calibration.procedure" in core and "gls_calibration.simulation.direct_cell" in core
    assert not any(name.startswith(("gls_calibration.nodes", "gls_calibration.cli")) for name in core)
    assert loaded_ros_packages(core) == []


def test_the_probe_sees_messages_when_a_node_module_is_imported():
    # The check above can fail: the message conversions do load rclpy's message packages.
    loaded = loaded_ros_packages(["gls_calibration.nodes.conversions"])
    assert "sensor_msgs" in loaded and "gls_calibration_msgs" in loaded
