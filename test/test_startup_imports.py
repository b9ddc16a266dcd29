"""Start-up: importing an executable does not load Open3D, which only a plane fit needs.

Open3D loads its plotting stack with it (about 1 s of CPU and 65 MB per process); every node and tool
imports ``PlatePose``, few fit a plane, and those load it at their first fit.
"""
from __future__ import annotations

from import_probe import loaded_roots, module_names

FIT = """
import numpy as np
from gls_calibration.scan.plate_pose import estimate_plate_pose
xy = np.random.default_rng(0).uniform(-50.0, 50.0, (2000, 2))
estimate_plate_pose(np.column_stack([xy, np.full(len(xy), 5.0)]))
"""


def test_no_executable_loads_open3d_at_import():
    # Every module of nodes/ and cli/: the executables' entry points and what they share.
    modules = [name for name in module_names(include_nodes=True)
               if name.startswith(("gls_calibration.nodes", "gls_calibration.cli"))]
    assert "gls_calibration.nodes.plate_pose" in modules and "gls_calibration.cli.sim_cell" in modules
    roots = loaded_roots(modules)
    assert "gls_calibration" in roots and "numpy" in roots
    assert "open3d" not in roots


def test_a_plane_fit_loads_open3d():
    # The check above can fail: the probe sees Open3D once a plane is fitted.
    assert "open3d" in loaded_roots([], then=FIT)
