"""package.xml as colcon, rosdep and ``ros2 run`` read it: well-formed XML naming an ament_python package.

An XML comment holding a double hyphen made it unreadable (2026-11-22 to 2026-11-23): colcon then built
the package as plain Python, with no ament index entry on AMENT_PREFIX_PATH, so ``ros2 run`` could
not find it and the installed nodes could not find their config files outside the source tree.
"""
from pathlib import Path
import xml.etree.ElementTree as ElementTree

MANIFEST = Path(__file__).resolve().parents[1] / "package.xml"


def test_the_manifest_is_well_formed_and_names_an_ament_python_package():
    root = ElementTree.parse(MANIFEST).getroot()     # raises ParseError on malformed XML
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == "gls_calibration"
    assert root.findtext("export/build_type") == "ament_python"
