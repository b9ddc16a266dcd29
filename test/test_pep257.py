"""ament_pep257 over the package: every check of the numpydoc convention, none left out.

Summaries are one line ending in a period, in the imperative for functions, methods and properties,
with closing quotes of multi-line docstrings on their own line; magic methods
(``__post_init__``, ``__repr__``, ...) have a docstring too.
"""
from pathlib import Path

from ament_pep257.main import main
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.linter
def test_pep257():
    rc = main(argv=["--convention", "numpy", "--", str(ROOT / "gls_calibration")])
    assert rc == 0, "docstring problems found (printed above)"
