"""ament_flake8 over the package, its tests and benchmarks, with the project's configuration (setup.cfg)."""
from pathlib import Path

from ament_flake8.main import main_with_errors
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.linter
def test_flake8():
    rc, errors = main_with_errors(argv=["--config", str(ROOT / "setup.cfg"),
                                        *(str(ROOT / part) for part in ("gls_calibration", "test", "benchmarks"))])
    assert rc == 0, f"{len(errors)} code style problem(s):\n" + "\n".join(errors)
