"""ament_python package gls_calibration.

Console scripts: `pip install -e .` (make setup) puts them in the venv's bin/; an install by colcon
puts them in lib/gls_calibration/, where `ros2 run gls_calibration <name>` looks. That option is
given here for `setup.py install` only (what colcon runs): in setup.cfg's [install], pip's editable
install read it too and put the venv's scripts in lib/. The extra "test" lists pytest, which makes
`colcon test` run pytest.
"""
from glob import glob
import sys

from setuptools import find_packages, setup

PACKAGE = "gls_calibration"

NODES = {
    "gls-scan-acquisition": "scan_acquisition",
    "gls-stream-acquisition": "stream_acquisition",
    "gls-plate-pose": "plate_pose",
    "gls-fiducial-measurement": "fiducial_measurement",
    "gls-rbf-trainer": "rbf_trainer",
    "gls-correction": "correction",
    "gls-calibration-manager": "calibration_manager",
    "gls-sim-galvo": "sim_galvo",
    "gls-sim-scanner": "sim_scanner",
}
TOOLS = {
    "gls-sim-cell": "sim_cell",
    "gls-calibrate": "calibrate",
    "gls-correct": "correct",
    "gls-export": "export",
    "gls-train": "train",
    "gls-discrepancy": "discrepancy",
    "gls-measure": "measure",
    "gls-reference-check": "reference_check",
}

ROS_INSTALL = {"install": {"install_scripts": f"$base/lib/{PACKAGE}"}} if "install" in sys.argv[1:] else {}

setup(
    name=PACKAGE,
    options=ROS_INSTALL,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.rviz") + glob("config/*.xml")),
    ],
    install_requires=["setuptools"],
    extras_require={"test": ["pytest", "pytest-timeout"]},
    zip_safe=False,
    maintainer="gls_calibration maintainers",
    maintainer_email="gls-calibration@example.com",
    description="In-situ calibration of a galvanometric laser scanner (ROS 2 Jazzy)",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [f"{script} = {PACKAGE}.nodes.{module}:main" for script, module in NODES.items()]
        + [f"{script} = {PACKAGE}.cli.{module}:main" for script, module in TOOLS.items()],
    },
)
