"""The simulated cell in one object, and its configuration file (``config/sim.yaml``).

The file is a ROS 2 parameter file; nested blocks are the dotted parameter names nodes see::

    /**:
      ros__parameters:
        seed: 1
        head: {working_distance_mm: 490.0, ...}     # nominal geometry, as in config/head.yaml
        effects: {galvo_gain_x: [0.0107], ...}      # TRUE effects of the simulated head (optics.EFFECTS)
        marking: {mark_speed_mm_s: 500.0, jump_time_s: 0.005}
        plate: {size_mm: 250.0, ...}                # pose comes from effects.plate_tilt / working_distance
        scanner: {standoff_mm: 325.0, ..., mounting_xyz_mm: [...], mounting_rpy_rad: [...],
                  mounting_error_xyz_mm: [...], mounting_error_rpy_rad: [...]}
        sweep: {length_mm: 210.0}
        measurement: {preset: paper_like}          # the measurement chain (simulation.measurement)

``measurement.preset`` is one of ``ideal``, ``careful``, ``paper_like`` (default) or ``custom``;
other keys of the block name single error sources (see :class:`MeasurementChain`).
"""
from __future__ import annotations

from dataclasses import dataclass, fields
import math
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from gls_calibration.common.config_files import config_path, read_config_file
from gls_calibration.geometry.head_config import effects_from_mapping, head_config_from_dict, parameters_block
from gls_calibration.geometry.kinematics import HeadGeometry, inverse
from gls_calibration.geometry.optics import HeadEffects
from gls_calibration.scan.sweep import SWEEP_LENGTH_MM, nominal_mounting
from gls_calibration.simulation.head import TruthHead
from gls_calibration.simulation.measurement import PRESET_CHAINS, MeasurementChain, measurement_from_mapping
from gls_calibration.simulation.plate import Plate, PlateSettings
from gls_calibration.simulation.scanner import LaserLineScanner, ScannerSettings, SweepData, pose_matrix

_PLATE_KEYS = tuple(f.name for f in fields(PlateSettings) if f.name not in ("tilt_x_rad", "tilt_y_rad", "delta_d_mm"))
_SCANNER_KEYS = tuple(f.name for f in fields(ScannerSettings))
_MOUNTING_KEYS = ("mounting_xyz_mm", "mounting_rpy_rad", "mounting_error_xyz_mm", "mounting_error_rpy_rad")
_MARKING_KEYS = ("mark_speed_mm_s", "jump_time_s")
_SWEEP_KEYS = ("length_mm",)


@dataclass(frozen=True, eq=False)
class SimConfig:
    """Everything that defines a simulated cell (mm, rad, s).

    Parameters
    ----------
    seed : int, default 1
        Seed of the cell's random draws.
    geometry : HeadGeometry, optional
        The nominal head.
    effects : HeadEffects, optional
        The true head's effects.
    mark_speed_mm_s : float, default 500.0
        Marking speed, mm/s; positive.
    jump_time_s : float, default 0.005
        Time of a jump between polylines, s; non-negative.
    plate : PlateSettings, optional
        The plate.
    scanner : ScannerSettings, optional
        The line scanner.
    scanner_to_gls : numpy.ndarray, shape (4, 4), optional
        The CAD mounting, scanner -> gls, mm; default: the scanner above the plate's centre.
    mounting_error : numpy.ndarray, shape (4, 4), optional
        The unknown mounting error in the scanner frame; default: none.
    sweep_length_mm : float, default SWEEP_LENGTH_MM
        Length of a sweep, mm; positive.
    measurement_preset : str, default "ideal"
        Name of the measurement chain's preset.
    measurement : MeasurementChain, optional
        The measurement chain.

    Raises
    ------
    ValueError
        If a speed, length or time is out of range.
    """

    seed: int = 1
    geometry: HeadGeometry = HeadGeometry()
    effects: HeadEffects = HeadEffects()
    mark_speed_mm_s: float = 500.0
    jump_time_s: float = 0.005
    plate: PlateSettings = PlateSettings()
    scanner: ScannerSettings = ScannerSettings()
    scanner_to_gls: np.ndarray = None          # 4x4 CAD mounting, scanner -> gls
    mounting_error: np.ndarray = None          # 4x4 unknown error in the scanner frame
    sweep_length_mm: float = SWEEP_LENGTH_MM
    measurement_preset: str = "ideal"
    measurement: MeasurementChain = PRESET_CHAINS["ideal"]

    def __post_init__(self) -> None:
        """Fill the default mountings and validate the fields (ValueError on the first bad one)."""
        if self.scanner_to_gls is None:
            object.__setattr__(self, "scanner_to_gls", pose_matrix(
                *nominal_mounting(self.sweep_length_mm, self.scanner.standoff_mm)))
        if self.mounting_error is None:
            object.__setattr__(self, "mounting_error", np.eye(4))
        for name in ("mark_speed_mm_s", "sweep_length_mm"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be positive, got {value!r}")
        if not (math.isfinite(self.jump_time_s) and self.jump_time_s >= 0.0):
            raise ValueError(f"jump_time_s must be non-negative, got {self.jump_time_s!r}")

    def plate_seed(self, plate_id: int) -> int | list[int]:
        """Seed of the plate with id ``plate_id`` loaded into this cell's fixture (0: the first one).

        The only rule for it: the galvo's plate and the scanner's copy of it (rebuilt from the id the
        galvo reports) must draw the same texture, marking-pose error, thermal scale and warp.
        """
        return self.seed if plate_id == 0 else [self.seed, int(plate_id)]

    def load_plate(self, plate: Plate, plate_id: int, marks: Iterable[np.ndarray] = ()) -> int:
        """Load plate ``plate_id`` of this cell's fixture into ``plate``, bearing ``marks``; return the id.

        The galvo's exchange (the next id, no marks) and every copy of its plate (the id and the marks
        the galvo reports) go through here, so that a copy draws what the galvo's plate drew.
        """
        plate.load_clean(self.plate_seed(plate_id), plate_id)
        for polyline in marks:
            plate.add_mark(polyline)
        return int(plate_id)

    def make_plate(self) -> Plate:
        """Return a plate of this configuration (with the measurement chain's mark and plate effects)."""
        return Plate(self.plate_settings, seed=self.plate_seed(0), chain=self.measurement,
                     beam_distance_mm=self.geometry.working_distance_mm + self.effects.get("working_distance")[0])

    def make_scanner(self) -> LaserLineScanner:
        """Return the scanner of this configuration (with the measurement chain's robot and sensor effects)."""
        return LaserLineScanner(self.scanner, self.scanner_to_gls, self.mounting_error, self.measurement,
                                robot_seed=self.seed)

    @property
    def plate_settings(self) -> PlateSettings:
        """Plate settings with the pose of the effects plate_tilt and working_distance."""
        tilt_x, tilt_y = self.effects.get("plate_tilt")
        return PlateSettings(**{**{key: getattr(self.plate, key) for key in _PLATE_KEYS},
                                "tilt_x_rad": tilt_x, "tilt_y_rad": tilt_y,
                                "delta_d_mm": self.effects.get("working_distance")[0]})


def default_sim_config_path() -> Path:
    """Return the package's ``config/sim.yaml``."""
    return config_path("sim.yaml")


def _block(parameters: Mapping[str, Any], name: str, known: Sequence[str]) -> dict[str, Any]:
    block = parameters.get(name) or {}
    if not isinstance(block, Mapping):
        raise ValueError(f"'{name}' must be a mapping, got {type(block).__name__}")
    unknown = sorted(set(block) - set(known))
    if unknown:
        raise ValueError(f"unknown {name} parameter(s) {', '.join(repr(f'{name}.{key}') for key in unknown)}; "
                         f"known: {', '.join(known)}")
    return dict(block)


def _number(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"sim parameter {key!r} must be a finite number, got {value!r}")
    return float(value)


def _triple(value: Any, key: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ValueError(f"sim parameter {key!r} must be a list of 3 numbers, got {value!r}")
    return np.array([_number(item, key) for item in value])


def sim_config_from_dict(document: Any, preset: str | None = None) -> SimConfig:
    """Build a SimConfig from a parsed sim configuration (see the module docstring).

    Missing keys take defaults. ``preset`` overrides ``measurement.preset`` of the document (e.g.
    from a command line).
    """
    parameters = parameters_block(document)
    known_blocks = ("seed", "head", "effects", "marking", "plate", "scanner", "sweep", "measurement")
    unknown = sorted(set(parameters) - set(known_blocks))
    if unknown:
        raise ValueError(f"unknown sim parameter(s) {', '.join(map(repr, unknown))}; known: {', '.join(known_blocks)}")
    head = parameters.get("head") or {}
    if isinstance(head, Mapping) and "effects" in head:
        raise ValueError("put the true effects of the simulated head under 'effects', not 'head.effects'")
    geometry, _ = head_config_from_dict({"head": head})

    effects = effects_from_mapping(parameters.get("effects"), "'effects'")

    seed = parameters.get("seed", 1)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"sim parameter 'seed' must be a non-negative integer, got {seed!r}")
    marking = {key: _number(value, f"marking.{key}")
               for key, value in _block(parameters, "marking", _MARKING_KEYS).items()}
    plate = _block(parameters, "plate", _PLATE_KEYS)
    plate = PlateSettings(**{key: _number(value, f"plate.{key}") for key, value in plate.items()})
    scanner = _block(parameters, "scanner", _SCANNER_KEYS + _MOUNTING_KEYS)
    mounting = {key: _triple(scanner.pop(key), f"scanner.{key}") for key in _MOUNTING_KEYS if key in scanner}
    scanner_values = {key: (int(value)
                            if key == "intensity_bits" and isinstance(value, int) and not isinstance(value, bool)
                            else _number(value, f"scanner.{key}"))
                      for key, value in scanner.items()}
    scanner = ScannerSettings(**scanner_values)
    sweep = {key: _number(value, f"sweep.{key}") for key, value in _block(parameters, "sweep", _SWEEP_KEYS).items()}
    length = sweep.get("length_mm", SWEEP_LENGTH_MM)
    preset, chain = measurement_from_mapping(parameters.get("measurement"), preset)

    cad = None
    if "mounting_xyz_mm" in mounting or "mounting_rpy_rad" in mounting:
        default_xyz_mm, default_rpy_rad = nominal_mounting(length, scanner.standoff_mm)
        cad = pose_matrix(mounting.get("mounting_xyz_mm", default_xyz_mm),
                          mounting.get("mounting_rpy_rad", default_rpy_rad))
    error = pose_matrix(mounting.get("mounting_error_xyz_mm", np.zeros(3)),
                        mounting.get("mounting_error_rpy_rad", np.zeros(3)))
    return SimConfig(seed=seed, geometry=geometry, effects=effects,
                     mark_speed_mm_s=marking.get("mark_speed_mm_s", 500.0),
                     jump_time_s=marking.get("jump_time_s", 0.005), plate=plate, scanner=scanner,
                     scanner_to_gls=cad, mounting_error=error, sweep_length_mm=length,
                     measurement_preset=preset, measurement=chain)


def load_sim_config(path: str | Path | None = None, preset: str | None = None) -> SimConfig:
    """Read a sim configuration file (default: the package's ``config/sim.yaml``).

    Parameters
    ----------
    path : str or pathlib.Path, optional
        The YAML file.
    preset : str, optional
        Overrides the file's ``measurement.preset``.

    Returns
    -------
    SimConfig
        The simulated cell.

    Raises
    ------
    ValueError
        With the file name for unreadable YAML, unknown keys or effect names, non-positive speeds or
        step sizes, unknown measurement presets, negative magnitudes and keys that conflict with the preset.
    """
    return read_config_file(path if path is not None else default_sim_config_path(), "sim configuration",
                            lambda document: sim_config_from_dict(document, preset))


class SimulatedCell:
    """Truth head, plate and scanner of one configuration, wired so that marks land on the plate.

    Parameters
    ----------
    config : SimConfig, optional
        The cell; the default one when None.

    Raises
    ------
    ValueError
        If the configuration's effects contradict its plate pose.
    """

    def __init__(self, config: SimConfig | None = None) -> None:
        self.config = config if config is not None else SimConfig()
        self.plate = self.config.make_plate()
        self.head = TruthHead(self.config.geometry, self.config.effects, plate=self.plate,
                              mark_speed_mm_s=self.config.mark_speed_mm_s, jump_time_s=self.config.jump_time_s)
        self.scanner = self.config.make_scanner()

    def exchange_plate(self) -> int:
        """Load a clean plate (new id, new texture, no marks); the marking clock keeps running."""
        return self.config.load_plate(self.plate, self.plate.plate_id + 1)

    def mark_cartesian(self, polylines_xy: Iterable, z: float = 0.0) -> list[np.ndarray]:
        """Mark polylines given in gls xy (M, 2) through the nominal inverse kinematics; landed (M, 3) each."""
        landed = []
        for polyline in polylines_xy:
            polyline = np.asarray(polyline, dtype=float)
            setpoints = inverse(self.config.geometry, polyline[:, 0], polyline[:, 1],
                                np.full(polyline.shape[0], float(z)))
            landed.append(self.head.mark(setpoints.alpha_x, setpoints.alpha_y))
        return landed

    def sweep_cloud(self, step_mm: float | None = None, seed: int | None = None, direction: int = 1,
                    orientation_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Return one sweep over the configured length placed by time.

        Organized xyz (H, W, 3) and intensity (H, W), in the sweep's start frame (the scanner base
        frame for the default sweep).
        """
        data = self.sweep_data(step_mm, seed, direction, orientation_deg)
        return data.xyz, data.intensity

    def sweep_data(self, step_mm: float | None = None, seed: int | None = None, direction: int = 1,
                   orientation_deg: float = 0.0) -> SweepData:
        """One sweep with stamps and the robot's reported poses (see :class:`SweepData`)."""
        seed = self.config.seed if seed is None else seed
        return self.scanner.sweep_data(self.plate, self.config.sweep_length_mm, step_mm=step_mm, seed=seed,
                                       direction=direction, orientation_deg=orientation_deg)

    def standstill_data(self, profiles: int, seed: int) -> SweepData:
        """Return ``profiles`` profiles with the robot standing still at the marking pose.

        The sensor stands over the middle of the sweep (see ``LaserLineScanner.standstill_data``):
        the plate as the head sees it.
        """
        return self.scanner.standstill_data(self.plate, profiles, seed=seed,
                                            position_mm=(0.0, 0.5 * self.config.sweep_length_mm, 0.0),
                                            marking_pose_error=self.plate.marking_pose_error)
