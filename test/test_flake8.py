"""ament_flake8 over the package, its tests and benchmarks, with the project's configuration (setup.cfg).

flake8 checks files in a pool of forked processes; forking this test process, which holds the ROS
middleware's threads of earlier tests, crashes the children. The linter runs in a fresh interpreter.
"""
from pathlib import Path
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINTER = "import sys; from ament_flake8.main import main; sys.exit(main())"


@pytest.mark.linter
def test_flake8():
    result = subprocess.run([sys.executable, "-c", LINTER, "--config", str(ROOT / "setup.cfg"),
                             *(str(ROOT / part) for part in ("gls_calibration", "test", "benchmarks"))],
                            capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, f"code style problems:\n{result.stdout[-6000:]}\n{result.stderr[-2000:]}"
