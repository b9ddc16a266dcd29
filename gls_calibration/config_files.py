"""Where the package's config/ files are: the source tree (editable install), else the share folder
of an installed package (colcon/ament)."""
from __future__ import annotations

from pathlib import Path


def config_path(name: str) -> Path:
    """Path of ``config/<name>``; FileNotFoundError naming the places looked at."""
    places = [Path(__file__).resolve().parent.parent / "config"]
    try:
        from ament_index_python.packages import get_package_share_directory
        places.append(Path(get_package_share_directory("gls_calibration")) / "config")
    except (ImportError, LookupError, OSError):  # not installed through ament, or no AMENT_PREFIX_PATH
        pass
    for place in places:
        if (place / name).is_file():
            return place / name
    raise FileNotFoundError(f"config file {name} not found in {', '.join(str(p) for p in places)}")
