"""ament_python package gls_calibration.

Console scripts go to the environment's bin/ (not lib/<package>/ as `ros2 run` expects) because
ros2cli is not available from PyPI: the operator tools and every node are started by name.
"""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "gls_calibration"

NODES = {
    "gls-scan-acquisition": "scan_acquisition",
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
}

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
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
