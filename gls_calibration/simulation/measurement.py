"""The measurement chain of the simulated cell: named error sources of robot, scanner, marks and plate.

Every source is a named magnitude (units in the name; zero switches it off) in the ``measurement``
block of ``config/sim.yaml``. A preset sets them all from physical causes:

- ``ideal``: every source off -- the algorithmic floor (the behaviour before the chain existed);
- ``careful``: a well-engineered cell: robot and timing errors about a third of ``paper_like``;
- ``paper_like``: the set-up of the published method, sized so that its reference-plate check,
  measured the paper's way (one sweep, profiles placed by time), gives 0.05-0.09 mm per axis;
- ``custom``: every source off unless given explicitly.

The robot (issue 32). What the controller REPORTS (encoders through the nominal kinematics) and where
the flange truly is differ by two kinds of error. The repeating kind (``robot_*``) comes from gearbox
transmission error, compliance and kinematic parameter errors: it is a function of where the arm is,
the same every time the arm runs the same programmed line in the same direction (ISO 9283 tells path
repeatability from path accuracy for this reason), so averaging repeated sweeps cannot remove it. The
simulator draws it once per cell (the sim ``seed``) as smooth fields over the base frame, one per
travel direction and sensor orientation. The random kind (``speed_ripple_mm`` of the timing,
``path_wander_mm`` and ``robot_along_wander_mm`` of the path) is drawn anew for every sweep. The
scanner's hand-eye error on the flange is ``scanner.mounting_error_*`` of ``config/sim.yaml``.

Explicit keys next to a named preset must agree with it (a conflict names the key); to give your
own values use ``preset: custom``. Random processes (speed ripple, path wander, mark wander,
width and darkness variation) are smooth: Gaussian-filtered white noise with the given standard
deviation and a Gaussian autocorrelation ``exp(-d^2 / (2 L^2))`` of correlation length ``L`` (mm).
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
import math
from typing import Any, Mapping

import numpy as np
from scipy.interpolate import RegularGridInterpolator
from scipy.ndimage import gaussian_filter, gaussian_filter1d

PRESETS = ("ideal", "careful", "paper_like", "custom")
DEFAULT_PRESET = "paper_like"

#: Keys that are on/off switches (0 or 1) rather than magnitudes.
SWITCHES = ("fan_geometry", "straight_rays")
#: The one signed key: a systematic error of the robot, not a magnitude.
SIGNED = ("speed_scale_error",)
#: The robot's repeating errors: the root sum of squares of their sizes over one sweep may not exceed
#: this (mm), the top of the paper's reference-plate band (0.091 / 0.086 mm per axis, k = 1): a robot
#: worse than that is not the published set-up, and a calibration against it states nothing useful.
ROBOT_REPEATING_LIMIT_MM = 0.09
#: Length (mm) over which ``robot_scale_error`` is counted in that budget: half the default sweep.
ROBOT_SCALE_ARM_MM = 100.0
#: (magnitude, correlation length) pairs: a magnitude above zero needs a positive correlation length.
CORRELATED = (("speed_ripple_mm", "speed_ripple_correlation_mm"),
              ("path_wander_mm", "path_wander_correlation_mm"),
              ("speckle_contrast", "speckle_correlation_mm"),
              ("mark_width_variation", "mark_variation_correlation_mm"),
              ("mark_darkness_variation", "mark_variation_correlation_mm"),
              ("mark_wander_mm", "mark_wander_correlation_mm"),
              ("robot_along_error_mm", "robot_along_correlation_mm"),
              ("robot_path_error_mm", "robot_path_correlation_mm"),
              ("robot_along_wander_mm", "path_wander_correlation_mm"))


@dataclass(frozen=True)
class MeasurementChain:
    """Magnitudes of the measurement-chain error sources (mm, rad, fractions; 0 switches one off)."""

    # a. robot placement of the profiles. Timing (what placement by time gets wrong; the encoders see it):
    speed_scale_error: float = 0.0            # true speed / assumed speed - 1 (signed, systematic)
    speed_ripple_mm: float = 0.0              # std of the along-sweep position error from speed ripple
    speed_ripple_correlation_mm: float = 0.0
    # reported versus true pose, drawn anew per sweep (the robot's path repeatability):
    path_wander_mm: float = 0.0               # std of the path's deviation across the sweep and in height
    path_wander_correlation_mm: float = 0.0
    robot_along_wander_mm: float = 0.0        # std of the along-travel error (correlation: path_wander's)
    # reported versus true pose, REPEATING per programmed line and direction (a function of where the arm is):
    robot_scale_error: float = 0.0            # std of the travel's scale error of one line (fraction)
    robot_along_error_mm: float = 0.0         # std of the along-travel error (transmission, compliance)
    robot_along_correlation_mm: float = 0.0
    robot_path_error_mm: float = 0.0          # std of the cross-track and of the height deviation
    robot_path_correlation_mm: float = 0.0
    # b-d. the sensor
    lateral_linearity_mm: float = 0.0         # peak of the fixed error along the laser line
    fan_geometry: float = 0.0                 # 1: points lie on rays from the laser's fan apex
    speckle_contrast: float = 0.0             # std of the correlated multiplicative speckle
    speckle_correlation_mm: float = 0.0
    blooming_mm: float = 0.0                  # spread (sigma) of saturated light along the line
    # e. marks as a laser makes them
    mark_width_variation: float = 0.0         # relative std of the line width along the path
    mark_darkness_variation: float = 0.0      # relative std of the darkening along the path
    mark_variation_correlation_mm: float = 0.0
    mark_wander_mm: float = 0.0               # std of the burnt line's deviation from the beam path
    mark_wander_correlation_mm: float = 0.0
    mark_blob_mm: float = 0.0                 # sigma of the dark blob where a mark starts and ends
    spot_blur_mm: float = 0.0                 # sigma of the blur by the spot size (adds to the line width)
    # f. plate to plate (drawn anew per plate)
    marking_height_mm: float = 0.0            # std of the plate height seen by the robot-held head when marking
    marking_tilt_rad: float = 0.0             # std of its tilt, about each axis
    thermal_scale_ppm: float = 0.0            # std of the plate's scale change between marking and scanning
    plate_warp_mm: float = 0.0                # peak out-of-plane warp of each plate
    # g. the head
    straight_rays: float = 0.0                # 1: in-plane head terms become deviations of straight rays

    def __post_init__(self) -> None:
        """Validate the fields and store bools as floats (ValueError on the first bad one)."""
        for item in fields(self):
            value = getattr(self, item.name)
            if isinstance(value, bool):
                object.__setattr__(self, item.name, float(value))
                value = float(value)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"measurement.{item.name} must be a finite number, got {value!r}")
            if item.name in SWITCHES and value not in (0.0, 1.0):
                raise ValueError(f"measurement.{item.name} is a switch: 0 (off) or 1 (on), got {value!r}")
            if item.name not in SIGNED and value < 0.0:
                raise ValueError(f"measurement.{item.name} must be non-negative, got {value!r}")
        if abs(self.speed_scale_error) >= 0.1:
            raise ValueError(f"measurement.speed_scale_error must be within +-0.1, got {self.speed_scale_error!r}")
        for name in ("marking_height_mm", "marking_tilt_rad"):
            if getattr(self, name) > 0.0 and not self.straight_rays:
                raise ValueError(f"measurement.{name} needs measurement.straight_rays = 1 (marks off the "
                                 "calibration plane follow the rays)")
        for magnitude, length in CORRELATED:
            if getattr(self, magnitude) > 0.0 and getattr(self, length) <= 0.0:
                raise ValueError(f"measurement.{length} must be positive when measurement.{magnitude} is set")
        repeating = math.sqrt(self.robot_along_error_mm ** 2 + self.robot_path_error_mm ** 2
                              + (self.robot_scale_error * ROBOT_SCALE_ARM_MM) ** 2)
        if repeating > ROBOT_REPEATING_LIMIT_MM:
            raise ValueError(
                f"measurement.robot_along_error_mm, measurement.robot_path_error_mm and "
                f"measurement.robot_scale_error (x {ROBOT_SCALE_ARM_MM:g} mm) add up to {repeating:.3g} mm, above "
                f"{ROBOT_REPEATING_LIMIT_MM:g} mm: the reference-plate check would leave the published band "
                f"(0.05-0.09 mm per axis)")

    @property
    def robot_repeats(self) -> bool:
        """Return True when the robot's reported pose carries an error that repeats per programmed line."""
        return bool(self.robot_scale_error or self.robot_along_error_mm or self.robot_path_error_mm)


#: The robot's repeating reported-versus-true error of ``paper_like`` (issue 32): a travel scale of
#: 2e-4 per line and a smooth 0.05 mm along-travel error of 20 mm correlation (the sizes with which
#: the seed-1..3 study reproduced the published 0.07 mm TRUE error; a 120 kg-class arm repeats its
#: path to +-0.05 mm but is accurate only to tenths of a millimetre, ISO 9283 path accuracy vs
#: repeatability), and a 0.03 mm cross-track / height deviation of 30 mm correlation (the part of a
#: path's deviation from its program that compliance and kinematic errors fix to the configuration;
#: the per-sweep ``path_wander_mm`` stays beside it). The per-sweep random along-travel part, 0.01 mm,
#: is a fifth of the +-0.05 mm repeatability.
_PAPER_ROBOT = dict(robot_scale_error=2.0e-4, robot_along_error_mm=0.05, robot_along_correlation_mm=20.0,
                    robot_path_error_mm=0.03, robot_path_correlation_mm=30.0, robot_along_wander_mm=0.01)

#: The timing ripple was 0.09 mm while it was the only along-track error; the repeating along-track
#: error now takes its share of the paper's along-track figure (0.086 mm): sqrt(0.09^2 - 0.05^2) = 0.075.
#: With 0.09 the reference check the paper's way gave a median of 0.093 mm in y over seeds 1-5, above the
#: published band; ripple only moves profiles placed by time, so placement by pose does not see it.
_PAPER_LIKE = MeasurementChain(
    speed_scale_error=3.0e-4, speed_ripple_mm=0.075, speed_ripple_correlation_mm=10.0,
    path_wander_mm=0.08, path_wander_correlation_mm=20.0,
    lateral_linearity_mm=0.065, fan_geometry=1.0, speckle_contrast=0.1, speckle_correlation_mm=0.1,
    blooming_mm=0.1,
    mark_width_variation=0.1, mark_darkness_variation=0.15, mark_variation_correlation_mm=1.0,
    mark_wander_mm=0.005, mark_wander_correlation_mm=1.0, mark_blob_mm=0.06, spot_blur_mm=0.02,
    marking_height_mm=0.017, marking_tilt_rad=3.0e-5, thermal_scale_ppm=12.0, plate_warp_mm=0.03,
    straight_rays=1.0, **_PAPER_ROBOT)

_ROBOT_AND_TIMING = ("speed_scale_error", "speed_ripple_mm", "path_wander_mm", "marking_height_mm",
                     "marking_tilt_rad", "robot_along_wander_mm", "robot_scale_error", "robot_along_error_mm",
                     "robot_path_error_mm")

PRESET_CHAINS: dict[str, MeasurementChain] = {
    "ideal": MeasurementChain(straight_rays=1.0),
    "paper_like": _PAPER_LIKE,
    "careful": replace(_PAPER_LIKE, **{name: getattr(_PAPER_LIKE, name) / 3.0 for name in _ROBOT_AND_TIMING}),
    "custom": MeasurementChain(),
}

KEYS = tuple(item.name for item in fields(MeasurementChain))


def measurement_from_mapping(block: Any, preset: str | None = None) -> tuple[str, MeasurementChain]:
    """Return (preset, chain) from a ``measurement`` block.

    ``preset`` (e.g. from the command line) overrides the block's own. ValueError names an unknown
    preset or key, a bad value or a conflict.
    """
    block = {} if block is None else block
    if not isinstance(block, Mapping):
        raise ValueError(f"'measurement' must be a mapping, got {type(block).__name__}")
    block = dict(block)
    name = block.pop("preset", DEFAULT_PRESET) if preset is None else preset
    block.pop("preset", None)
    if name not in PRESETS:
        raise ValueError(f"unknown measurement preset {name!r}; known: {', '.join(PRESETS)}")
    unknown = sorted(set(block) - set(KEYS))
    if unknown:
        raise ValueError(f"unknown measurement parameter(s) {', '.join(repr(f'measurement.{k}') for k in unknown)}; "
                         f"known: preset, {', '.join(KEYS)}")
    base = PRESET_CHAINS[name]
    for key, value in block.items():
        if isinstance(value, bool):
            value = float(value)
        if not isinstance(value, (int, float)):
            raise ValueError(f"measurement.{key} must be a finite number, got {value!r}")
        if name != "custom" and not math.isclose(float(value), getattr(base, key), rel_tol=1e-9, abs_tol=1e-15):
            raise ValueError(f"measurement.{key} = {value!r} conflicts with preset {name!r} "
                             f"({getattr(base, key)!r}); use preset: custom to give your own values")
    return name, replace(base, **{key: float(value) for key, value in block.items()})


def smooth_process(rng: np.random.Generator, positions_mm, std: float, correlation_mm: float) -> np.ndarray:
    """Sample a smooth zero-mean random process at ``positions_mm``.

    Positions may come in any order; standard deviation ``std``, Gaussian autocorrelation of length
    ``correlation_mm``. Zeros when ``std`` is 0.
    """
    positions = np.asarray(positions_mm, dtype=float)
    if std == 0.0 or positions.size == 0:
        return np.zeros_like(positions)
    spacing = correlation_mm / 8.0
    low, high = float(positions.min()) - 4.0 * correlation_mm, float(positions.max()) + 4.0 * correlation_mm
    count = int(math.ceil((high - low) / spacing)) + 2
    kernel_sigma = correlation_mm / math.sqrt(2.0) / spacing    # autocorrelation sigma = sqrt(2) * kernel sigma
    filtered = gaussian_filter1d(rng.standard_normal(count), kernel_sigma, mode="wrap")
    # unit variance: divide by the norm of the discrete kernel
    impulse = np.zeros(count)
    impulse[count // 2] = 1.0
    norm = math.sqrt(float(np.sum(gaussian_filter1d(impulse, kernel_sigma, mode="wrap") ** 2)))
    grid = low + spacing * np.arange(count)
    return std / norm * np.interp(positions, grid, filtered)


FIELD_HALF_SPAN_MM = 400.0
"""Half the side of the square of the base frame (centred on its origin) that a robot field covers."""


def smooth_field(rng: np.random.Generator, std: float, correlation_mm: float):
    """Return a smooth zero-mean random field over the base frame's x-y: a function ``f(xy_mm) -> (N,)``.

    Standard deviation ``std``, Gaussian autocorrelation ``exp(-d^2 / (2 L^2))`` of length
    ``correlation_mm`` in every direction, over the square of half-side :data:`FIELD_HALF_SPAN_MM`
    about the origin (ValueError outside it). The field is fixed at construction, so every query
    of a position gives the same value: what a robot's repeating error needs. Zeros when ``std`` is 0.
    """
    if std == 0.0:
        return lambda xy_mm: np.zeros(np.asarray(xy_mm, dtype=float).shape[0])
    spacing = correlation_mm / 8.0
    count = int(math.ceil(2.0 * FIELD_HALF_SPAN_MM / spacing)) + 1
    kernel_sigma = correlation_mm / math.sqrt(2.0) / spacing
    filtered = gaussian_filter(rng.standard_normal((count, count)), kernel_sigma, mode="wrap")
    impulse = np.zeros(int(2 * math.ceil(4.0 * kernel_sigma) + 1))
    impulse[impulse.size // 2] = 1.0
    # 2-D: product of two 1-D norms
    norm = float(np.sum(gaussian_filter1d(impulse, kernel_sigma, mode="constant") ** 2))
    values = std / norm * filtered
    axis = -FIELD_HALF_SPAN_MM + spacing * np.arange(count)
    interpolate = RegularGridInterpolator((axis, axis), values, method="linear", bounds_error=True)

    def field(xy_mm) -> np.ndarray:
        xy = np.asarray(xy_mm, dtype=float).reshape(-1, 2)
        if np.any(np.abs(xy) > FIELD_HALF_SPAN_MM - spacing):
            raise ValueError(f"a robot position lies outside the simulated robot's field of "
                             f"+-{FIELD_HALF_SPAN_MM:g} mm about the base frame's origin")
        return interpolate(xy)

    return field


def lateral_linearity_shape(x_mm, half_length_mm: float) -> np.ndarray:
    """Return the sensor's fixed lateral linearity shape along the line, peak 1 over ``|x| <= half_length_mm``.

    A property of the sensor, the same in every sweep: a smooth mix of low orders (its linear part
    is a scale error of the line, as a real sensor's calibration leaves one).
    """
    s = np.asarray(x_mm, dtype=float) / half_length_mm
    shape = 0.55 * np.sin(0.5 * np.pi * s) + 0.35 * np.sin(1.3 * np.pi * s + 0.7) + 0.25 * np.cos(2.2 * np.pi * s)
    peak = np.max(np.abs(0.55 * np.sin(0.5 * np.pi * _UNIT) + 0.35 * np.sin(1.3 * np.pi * _UNIT + 0.7)
                         + 0.25 * np.cos(2.2 * np.pi * _UNIT)))
    return shape / peak


_UNIT = np.linspace(-1.0, 1.0, 2001)
