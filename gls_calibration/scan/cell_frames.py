"""The cell's fixed frames from one YAML file (``config/cell_frames.yaml``).

Frame names, the hand-eye mounting (sensor optical frame in the flange frame) and the galvo head in
the robot base frame.

The robot node publishes both poses on ``/tf_static``; the streaming acquisition reads the frame
names. Poses in the file are in metres and radians (REP 103); :class:`CellFrames` holds them as 4x4
matrices in mm, as the rest of the package does.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from gls_calibration.common.config_files import config_path, read_config_file, require_exact_keys

MM_PER_M = 1000.0
FRAME_KEYS = ("base", "flange", "sensor", "gls")
POSE_KEYS = ("translation_m", "rpy_rad")
MAX_TRANSLATION_M = 100.0    # a cell is metres across: a larger offset is a unit mistake (mm?)


@dataclass(frozen=True)
class CellFrames:
    """Frame names and the two fixed poses (child in parent, 4x4, mm)."""

    base: str
    flange: str
    sensor: str
    gls: str
    flange_to_sensor: np.ndarray
    base_to_gls: np.ndarray


def _pose(block: Any, name: str) -> np.ndarray:
    if not isinstance(block, dict):
        raise ValueError(f"{name} must be a mapping with {', '.join(POSE_KEYS)}")
    require_exact_keys(block, POSE_KEYS, name)
    values = {}
    for key in POSE_KEYS:
        value = block[key]
        if (not isinstance(value, list) or len(value) != 3
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                           for v in value)):
            raise ValueError(f"{name}.{key} must be a list of 3 finite numbers, got {value!r}")
        values[key] = np.array(value, dtype=float)
    if np.max(np.abs(values["translation_m"])) > MAX_TRANSLATION_M:
        raise ValueError(f"{name}.translation_m {values['translation_m'].tolist()} is beyond {MAX_TRANSLATION_M:g} m: "
                         "it must be in metres")
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", values["rpy_rad"]).as_matrix()
    pose[:3, 3] = values["translation_m"] * MM_PER_M
    return pose


def cell_frames_from_dict(document: Any) -> CellFrames:
    """:class:`CellFrames` of a parsed YAML document; ValueError naming the first problem."""
    if not isinstance(document, dict):
        raise ValueError("the cell frames file must be a mapping with frames, flange_to_sensor, base_to_gls")
    require_exact_keys(document, ("frames", "flange_to_sensor", "base_to_gls"), "cell")
    frames = document["frames"]
    if not isinstance(frames, dict):
        raise ValueError(f"frames must be a mapping with {', '.join(FRAME_KEYS)}")
    require_exact_keys(frames, FRAME_KEYS, "frames")
    for key in FRAME_KEYS:
        name = frames[key]
        if not isinstance(name, str) or not name or name.startswith("/") or any(c.isspace() for c in name):
            raise ValueError(f"frames.{key} must be a non-empty frame name without spaces or a leading '/', "
                             f"got {name!r}")
    if len(set(frames[key] for key in FRAME_KEYS)) != len(FRAME_KEYS):
        raise ValueError(f"frames must be four different names, got {[frames[key] for key in FRAME_KEYS]}")
    return CellFrames(*(frames[key] for key in FRAME_KEYS), _pose(document["flange_to_sensor"], "flange_to_sensor"),
                      _pose(document["base_to_gls"], "base_to_gls"))


def load_cell_frames(path: str | Path | None = None) -> CellFrames:
    """Return the cell frames file at ``path`` (None: the package's ``config/cell_frames.yaml``).

    Parameters
    ----------
    path : str or pathlib.Path, optional
        The YAML file (poses in metres and radians).

    Returns
    -------
    CellFrames
        The frame names and the poses as 4x4 matrices (mm).

    Raises
    ------
    ValueError
        Naming the file and the first problem: unreadable file or YAML, a missing or bad key, a bad
        frame name, a translation beyond ``MAX_TRANSLATION_M``.
    """
    return read_config_file(config_path("cell_frames.yaml") if path is None else path, "cell frames file",
                            cell_frames_from_dict)
