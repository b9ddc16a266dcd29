"""The package's modules by name, and which top-level modules a fresh interpreter loads with them.

Shared by the layering test (no rclpy in the core) and the start-up test (no Open3D at import).
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
for name in sys.argv[2:]:
    importlib.import_module(name)
exec(sys.argv[1])
print(json.dumps(sorted({name.split(".")[0] for name in sys.modules})))
"""


def module_name_of(path: Path) -> str:
    """The dotted module name of a file of the package."""
    parts = path.relative_to(PACKAGE).with_suffix("").parts
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(("gls_calibration",) + parts)


def module_names(include_nodes: bool) -> list[str]:
    """Every module of the package; without ros/, nodes/ and cli/ unless ``include_nodes``."""
    return [module_name_of(path) for path in sorted(PACKAGE.rglob("*.py"))
            if include_nodes or path.relative_to(PACKAGE).parts[0] not in ("ros", "nodes", "cli")]


def loaded_roots(modules: list[str], then: str = "") -> list[str]:
    """Top-level modules in sys.modules of a fresh interpreter after importing ``modules`` and running ``then``."""
    result = subprocess.run([sys.executable, "-c", PROBE, then, *modules], capture_output=True, text=True,
                            check=True, timeout=300)
    return json.loads(result.stdout)
