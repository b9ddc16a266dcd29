"""ament_pep257 over the package: the numpydoc convention's checks that its docstrings meet.

Not checked yet (a known gap, docs/architecture.md): the summary of many docstrings runs over
several lines (D205, D400, D415), is not in the imperative (D401) or closes its quotes on the last
text line (D209); magic methods (``__post_init__``, ``__repr__``, ...) may go without one (D105).
"""
from pathlib import Path

from ament_pep257.main import main
import pytest

ROOT = Path(__file__).resolve().parents[1]
NOT_YET = ["D105"]


@pytest.mark.linter
def test_pep257():
    rc = main(argv=["--convention", "numpy", "--add-ignore", *NOT_YET, "--", str(ROOT / "gls_calibration")])
    assert rc == 0, "docstring problems found (printed above)"
