"""The package's layers: the core (all but ros/, nodes/ and cli/) never loads rclpy or message packages,
and the stage folders import only the stages before them, without circles."""
from __future__ import annotations

import ast
from pathlib import Path

from import_probe import PACKAGE, loaded_roots, module_name_of, module_names

ROS_ROOTS = ("rclpy", "rcl_interfaces", "builtin_interfaces", "std_srvs", "rosidl_runtime_py")


def loaded_ros_packages(modules: list[str]) -> list[str]:
    """Top-level ROS packages in sys.modules of a fresh interpreter after importing ``modules``."""
    return [root for root in loaded_roots(modules) if root in ROS_ROOTS or root.endswith("_msgs")]


def test_core_modules_import_neither_rclpy_nor_messages():
    core = module_names(include_nodes=False)
    assert "gls_calibration.calibration.procedure" in core and "gls_calibration.simulation.direct_cell" in core
    assert not any(name.startswith(("gls_calibration.ros", "gls_calibration.nodes", "gls_calibration.cli"))
                   for name in core)
    assert loaded_ros_packages(core) == []


def test_the_probe_sees_messages_when_a_node_module_is_imported():
    # The check above can fail: the message conversions do load rclpy's message packages.
    loaded = loaded_ros_packages(["gls_calibration.ros.conversions"])
    assert "sensor_msgs" in loaded and "gls_calibration_msgs" in loaded


# The stages in pipeline order: a module may import its own stage and the stages before it, never
# one after it (``common`` is under everything; the ROS machinery, the executables and the tools
# sit on top of the core). The package's top-level ``__init__`` holds only the version.
STAGES = ("common", "geometry", "scan", "fiducials", "registration", "discrepancy", "models", "correction",
          "calibration", "report", "simulation", "ros", "nodes", "cli")


def _stage(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def imports_of(path: Path) -> set[str]:
    """Every ``gls_calibration`` module ``path`` imports, anywhere in it (functions and TYPE_CHECKING blocks too)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.startswith("gls_calibration."))
        elif (isinstance(node, ast.ImportFrom) and node.level == 0
              and (node.module or "").startswith("gls_calibration.")):
            base = node.module
            for alias in node.names:   # ``from pkg import module`` names a module; else the module itself
                candidate = f"{base}.{alias.name}"
                found.add(candidate if candidate in ALL_MODULES else base)
    return found


ALL_MODULES = set(module_names(include_nodes=True))


def test_every_module_lives_in_a_stage_folder():
    loose = sorted(name for name in ALL_MODULES if _stage(name) not in STAGES and name != "gls_calibration")
    assert loose == []


def test_no_stage_imports_a_later_stage():
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = module_name_of(path)
        if module == "gls_calibration":
            continue
        for imported in imports_of(path):
            if STAGES.index(_stage(imported)) > STAGES.index(_stage(module)):
                offenders.append(f"{module} imports {imported}")
    assert offenders == []


def test_no_import_circle():
    graph = {module_name_of(path): imports_of(path) for path in PACKAGE.rglob("*.py")}
    circles = []

    def visit(module, trail):
        for imported in sorted(graph.get(module, ())):
            if imported in trail:
                circles.append(" -> ".join(trail[trail.index(imported):] + [imported]))
            elif imported not in done:
                visit(imported, trail + [imported])
        done.add(module)

    done: set[str] = set()
    for module in sorted(graph):
        if module not in done:
            visit(module, [module])
    assert circles == []


def test_the_checks_see_a_late_import_and_a_circle(tmp_path):
    # The two checks above can fail: a core module importing a node, and two modules importing each other.
    late = tmp_path / "late.py"
    late.write_text("def f():\n    from gls_calibration.nodes import calibration_manager\n")
    assert "gls_calibration.nodes.calibration_manager" in imports_of(late)
    assert STAGES.index(_stage("gls_calibration.nodes.calibration_manager")) > STAGES.index("models")
    typed = tmp_path / "typed.py"
    typed.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                     "    from gls_calibration.calibration.procedure import ProcedureSettings\n")
    assert imports_of(typed) == {"gls_calibration.calibration.procedure"}


def private_names_imported(path: Path) -> list[str]:
    """The underscore names ``path`` imports from other modules of the package (``module.name``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    return [f"{node.module}.{alias.name}" for node in ast.walk(tree)
            if isinstance(node, ast.ImportFrom) and node.level == 0
            and (node.module or "").startswith("gls_calibration.")
            for alias in node.names if alias.name.startswith("_") and not alias.name.startswith("__")]


def test_no_module_imports_another_modules_private_name(tmp_path):
    # A name another module uses is part of its module's interface: it goes without the underscore.
    offenders = [f"{module_name_of(path)} imports {name}" for path in sorted(PACKAGE.rglob("*.py"))
                 for name in private_names_imported(path)]
    assert offenders == []
    sample = tmp_path / "sample.py"
    sample.write_text("from gls_calibration.fiducials.ring_fit import refine_ring_centres, _private\n")
    assert private_names_imported(sample) == ["gls_calibration.fiducials.ring_fit._private"]
