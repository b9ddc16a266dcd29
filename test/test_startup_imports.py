"""Start-up: importing an executable does not load Open3D, which only a plane fit needs.

Open3D loads its plotting stack with it (about 1 s of CPU and 60 MB per process); every node and tool
imports ``PlatePose``, few fit a plane, and those load it at their first fit.
"""
from __future__ import annotations

import json
from pathlib import Path
import subprocess
import sys

import gls_calibration

PACKAGE = Path(gls_calibration.__file__).parent

PROBE = """
import importlib, json, sys
for name in sys.argv[1:]:
    importlib.import_module(name)
print(json.dumps(sorted({name.split(".")[0] for name in sys.modules})))
"""

FIT = """
import json, sys
import numpy as np
from gls_calibration.scan.plate_pose import estimate_plate_pose
xy = np.random.default_rng(0).uniform(-50.0, 50.0, (2000, 2))
estimate_plate_pose(np.column_stack([xy, np.full(len(xy), 5.0)]))
print(json.dumps(sorted({name.split(".")[0] for name in sys.modules})))
"""


def executable_modules() -> list[str]:
    """Every module under nodes/ and cli/ (the executables' entry points and what they share)."""
    return sorted(".".join(("gls_calibration",) + path.relative_to(PACKAGE).with_suffix("").parts)
                  for folder in ("nodes", "cli") for path in (PACKAGE / folder).glob("*.py")
                  if path.stem != "__init__")


def loaded_roots(code: str, *arguments: str) -> list[str]:
    """Top-level modules in sys.modules of a fresh interpreter after running ``code``."""
    result = subprocess.run([sys.executable, "-c", code, *arguments], capture_output=True, text=True,
                            check=True, timeout=300)
    return json.loads(result.stdout)


def test_no_executable_loads_open3d_at_import():
    modules = executable_modules()
    assert "gls_calibration.nodes.plate_pose" in modules and "gls_calibration.cli.sim_cell" in modules
    roots = loaded_roots(PROBE, *modules)
    assert "gls_calibration" in roots and "numpy" in roots
    assert "open3d" not in roots


def test_a_plane_fit_loads_open3d():
    # The check above can fail: the probe sees Open3D once a plane is fitted.
    assert "open3d" in loaded_roots(FIT)
