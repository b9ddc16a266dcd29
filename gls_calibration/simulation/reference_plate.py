"""Reference-plate check of the simulated measurement chain (the published set-up's §3.2, simulated).

A reference plate with known centres -- our own double-ring fiducials (radii 2.5 and 2.7 mm, the
calibration's), 13 x 11 at a 10 mm pitch (120 x 100 mm), as precise as a certified plate: its marks
carry none of the marking effects and it is neither warm nor warped -- is laid at several positions
in the field and scanned by the simulated robot and scanner with the whole measurement chain. Each
position's measured centres (gls frame through the CAD mounting) are paired with the known ones and
aligned by a best 2-D rigid motion (where a plate lies is unknown); the residuals give the standard
uncertainty per axis (k = 1, pooled over positions, the alignment's 3 degrees of freedom per position
taken out) and the bias per position (mean residual after ONE rigid alignment of all positions, what
a position-dependent error leaves).

Two measurement plans are compared: ``RAW_PLAN``, the paper's way (one sweep, profiles placed by
time at the nominal speed, the plate plane from that sweep), and the plan the calibration runs
(:func:`calibration_plan`: the calibration manager's ``sweep.plan``, ``sweep.placed_by_pose`` and
``sweep.plain_repeats`` from its parameter file, ``config/gls.yaml`` -- today three passes, 0+,90+,45+,
placed by the robot's reported pose). A plan's sweeps are combined by the calibration's own code
(``procedure.combined_centres_gls``: the error separation of ``sweep_plan.combine_sweeps``) and
paired with the known centres as the calibration pairs its targets; the plate plane comes from
plain sweeps averaged as the calibration does.

:func:`measure_chain_map` sweeps the same kind of plate along the calibration's lines on the same
simulated robot and fits the lines' repeating error (``registration/chain_map.py``); a check made with that map
applied (``chain_map`` of :func:`reference_plate_check`) is what a calibration run with the map may
state its accuracy from.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np

from gls_calibration.calibration.procedure import ProcedureSettings
from gls_calibration.calibration.reference_check import (aligned_residuals, chain_sigma_mm, measure_reference_plate,
                                                         plate_plane)
from gls_calibration.calibration.stated_accuracy import ChainCheck, centres_extent_mm
from gls_calibration.common.config_files import config_path, read_config_file
from gls_calibration.common.validation import as_integer_at_least, as_positive_number
from gls_calibration.fiducials import targets
from gls_calibration.fiducials.measure import measure_fiducials
from gls_calibration.geometry.head_config import parameters_block
from gls_calibration.registration.chain_map import (ChainMap, ChainMapFit, ReferenceSweep, chain_map_identity,
                                                    fit_chain_map)
from gls_calibration.registration.rigid import RigidTransform, pair_with_targets
from gls_calibration.registration.sweep_plan import CellTimeModel, SweepPass, parse_plan, plan_label
from gls_calibration.simulation.plate import Plate
from gls_calibration.simulation.world import SimConfig

RING_RADII_MM = targets.RING_RADII_MM
PATTERN = (13, 11)                  # rings along x, along y
PITCH_MM = 10.0
POSITIONS_MM = ((-40.0, -40.0), (0.0, 0.0), (40.0, 40.0))


@dataclass(frozen=True)
class ReferencePlateDesign:
    """A plate with known centres: rings per side (x, y), pitch (mm), plate-centre positions (mm)."""

    pattern: tuple[int, int] = PATTERN
    pitch_mm: float = PITCH_MM
    positions_mm: tuple[tuple[float, float], ...] = POSITIONS_MM

    @property
    def label(self) -> str:
        """Short description of the plate: pattern, pitch and positions."""
        return (f"{self.pattern[0]} x {self.pattern[1]} double rings at {self.pitch_mm:g} mm, "
                f"{len(self.positions_mm)} position{'s' if len(self.positions_mm) > 1 else ''}")


#: The published check: a 120 x 100 mm plate at three positions on the diagonal.
PAPER_PLATE = ReferencePlateDesign()


def field_plate(settings: ProcedureSettings = ProcedureSettings()) -> ReferencePlateDesign:
    """Return the certified plate over the calibrated field: its rings where the calibration grid's are.

    The chain's repeating error is a field over the robot's lines whose scale and shear part grows
    towards the lines' ends, so only a plate that reaches as far as the calibration's marks measures
    what they carry: a 180 mm plate (19 x 19 at 10 mm) under a 190 mm grid showed 57 % of it on one
    simulated cell (``paper_like`` and ``careful`` seed 4, where the robot's along-travel trend over
    +-90 mm and over +-95 mm differs by 130 ppm), 97-100 % on the others.

    Parameters
    ----------
    settings : ProcedureSettings, optional
        The calibration's grid (``grid_per_side``, ``grid_size_mm``); default the shipped one.

    Returns
    -------
    ReferencePlateDesign
        ``grid_per_side`` rings a side at the grid's pitch, centred on the field, in one position.

    Examples
    --------
    >>> field_plate().label
    '19 x 19 double rings at 10.5556 mm, 1 position'
    """
    per_side = settings.grid_per_side
    return ReferencePlateDesign(pattern=(per_side, per_side), pitch_mm=settings.grid_size_mm / (per_side - 1),
                                positions_mm=((0.0, 0.0),))


#: The simulated cells' certified plate: over the shipped calibration grid (:func:`field_plate`).
FIELD_PLATE = field_plate()


@dataclass(frozen=True)
class MeasurementPlan:
    """How a plate is measured: passes, profile placement, plain sweeps and profile steps.

    How a plate is measured: the passes over it (``sweep_plan.SweepPass``), profiles placed by the
    robot's reported pose or by time, the plain sweeps whose plate planes are averaged (0: the
    plane of the first pass), and the sweeps' profile steps (plain and marked plate).
    """

    passes: tuple[SweepPass, ...] = (SweepPass(),)
    placed_by_pose: bool = False
    plain_sweeps: int = 0
    plain_step_mm: float = ProcedureSettings.plain_sweep_step_mm
    marked_step_mm: float = ProcedureSettings.marked_sweep_step_mm

    def __post_init__(self) -> None:
        """Validate the fields (ValueError on the first bad one)."""
        if not self.passes or not all(isinstance(item, SweepPass) for item in self.passes):
            raise ValueError(f"a plan needs one or more SweepPass, got {self.passes!r}")
        if not isinstance(self.placed_by_pose, bool):
            raise ValueError(f"placed_by_pose must be true or false, got {self.placed_by_pose!r}")
        as_integer_at_least(self.plain_sweeps, "plain_sweeps", 0)
        as_positive_number(self.plain_step_mm, "plain_step_mm")
        as_positive_number(self.marked_step_mm, "marked_step_mm")

    @property
    def placement(self) -> str:
        """How the profiles are placed: ``pose`` (reported pose) or ``time`` (nominal speed)."""
        return "pose" if self.placed_by_pose else "time"

    @property
    def label(self) -> str:
        """Short name of the sweep plan, such as ``0+,90+``."""
        return plan_label(self.passes)


RAW_PLAN = MeasurementPlan()


def calibration_plan(parameter_file: str | Path | None = None) -> MeasurementPlan:
    """Return the plan the calibration manager runs with ``parameter_file``.

    It reads ``sweep.plan``, ``sweep.placed_by_pose``, ``sweep.plain_repeats``, ``sweep.plain_step_mm``
    and ``sweep.marked_step_mm``, with the procedure's defaults for keys the file leaves out.

    Parameters
    ----------
    parameter_file : str or pathlib.Path, optional
        A parameter file; default: the package's ``config/gls.yaml``.

    Returns
    -------
    MeasurementPlan
        The passes, placement, plain sweeps and profile steps.

    Raises
    ------
    ValueError
        Naming the file and key.
    """
    defaults = ProcedureSettings()

    def parse(document: Any) -> MeasurementPlan:
        sweep = parameters_block(document).get("sweep") or {}
        if not isinstance(sweep, Mapping):
            raise ValueError(f"sweep must be a mapping, got {type(sweep).__name__}")
        passes = parse_plan(sweep["plan"]) if "plan" in sweep else defaults.sweep_plan
        return MeasurementPlan(passes, sweep.get("placed_by_pose", defaults.profiles_placed_by_pose),
                               sweep.get("plain_repeats", defaults.plain_sweeps),
                               sweep.get("plain_step_mm", defaults.plain_sweep_step_mm),
                               sweep.get("marked_step_mm", defaults.marked_sweep_step_mm))

    return read_config_file(parameter_file if parameter_file is not None else config_path("gls.yaml"),
                            "parameter file", parse)


@dataclass(frozen=True)
class ReferencePlateResult:
    """Standard uncertainty (k = 1) and bias per axis (gls x, y), mm, of one plan.

    ``known_xy_mm`` and ``residuals_mm`` (N, 2) are the known centres found and their residuals
    after each position's best rigid motion (None when not kept), for studies of the check's field.
    """

    sigma_mm: tuple[float, float]
    bias_mm: tuple[tuple[float, float], ...]    # per position
    found: int
    expected: int
    known_xy_mm: Optional[np.ndarray] = None
    residuals_mm: Optional[np.ndarray] = None


def reference_pattern(design: ReferencePlateDesign = PAPER_PLATE) -> np.ndarray:
    """Known centres (N, 2) of the reference pattern about its own centre, mm."""
    nx, ny = design.pattern
    u = (np.arange(nx) - 0.5 * (nx - 1)) * design.pitch_mm
    v = (np.arange(ny) - 0.5 * (ny - 1)) * design.pitch_mm
    return np.array([(a, b) for b in v for a in u])


def _reference_plate(config: SimConfig, offset_xy, seed,
                     design: ReferencePlateDesign = PAPER_PLATE) -> tuple[Plate, np.ndarray]:
    chain = replace(config.measurement, mark_width_variation=0.0, mark_darkness_variation=0.0,
                    mark_wander_mm=0.0, mark_blob_mm=0.0, spot_blur_mm=0.0, thermal_scale_ppm=0.0,
                    plate_warp_mm=0.0)
    plate = Plate(config.plate_settings, seed=seed, chain=chain)
    known_uv = reference_pattern(design) + np.asarray(offset_xy, dtype=float)
    for ring in targets.rings_polylines(known_uv, RING_RADII_MM):
        plate.add_mark_plate(ring)
    return plate, plate.from_plate(known_uv)


def measure_plate(config: SimConfig, plate: Plate, plan: MeasurementPlan, seed: int,
                  known_gls: np.ndarray, chain_map: ChainMap | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Measure ``plate`` with ``plan`` as the calibration measures its marked plate.

    ``chain_map``, when given, is removed from every sweep. Returns the measured centres (M, 3, gls
    frame through the CAD mounting) and the known ones (M, 3) they pair with.
    """
    scanner = config.make_scanner()
    mounting = config.scanner_to_gls
    settings = ProcedureSettings(ring_radii_mm=RING_RADII_MM, sweep_plan=plan.passes,
                                 profiles_placed_by_pose=plan.placed_by_pose,
                                 scanner_to_gls=RigidTransform(mounting[:3, :3].copy(), mounting[:3, 3].copy()),
                                 chain_map=chain_map,
                                 cell_time=CellTimeModel(sweep_length_mm=config.sweep_length_mm))

    def cloud(number: int, step_mm: float, item: SweepPass = SweepPass()) -> tuple[np.ndarray, np.ndarray]:
        data = scanner.sweep_data(plate, config.sweep_length_mm, step_mm=step_mm, seed=seed * 1009 + number,
                                  direction=item.direction, orientation_deg=item.orientation_deg)
        return (data.placed_by_pose() if plan.placed_by_pose else data.placed_by_time()), data.intensity

    plain = (cloud(500 + repeat, plan.plain_step_mm)[0] for repeat in range(plan.plain_sweeps))
    passes = (cloud(number, plan.marked_step_mm, item) for number, item in enumerate(plan.passes))
    return measure_reference_plate(plain, passes, settings, known_gls)


def reference_plate_check(config: SimConfig, plan: MeasurementPlan, seed: int = 1,
                          positions=None, design: ReferencePlateDesign = PAPER_PLATE,
                          chain_map: ChainMap | None = None) -> ReferencePlateResult:
    """Scan the reference plate ``design`` at ``positions`` with ``plan``.

    Parameters
    ----------
    config : SimConfig
        The simulated cell.
    plan : MeasurementPlan
        How each placement is measured.
    seed : int, default 1
        Seed of the plates and sweeps.
    positions : sequence of (float, float), optional
        Plate-centre offsets, mm; None: the design's.
    design : ReferencePlateDesign, default PAPER_PLATE
        The plate with known centres.
    chain_map : ChainMap, optional
        Removed from every sweep: a calibration that runs with a chain map must state its accuracy
        from a check made with it.

    Returns
    -------
    ReferencePlateResult
        Standard uncertainty (k = 1) and bias per axis, mm, and the centres found and expected.
    """
    positions = design.positions_mm if positions is None else positions
    measured_all, known_all, found, expected = [], [], 0, 0
    for index, offset in enumerate(positions):
        plate, known = _reference_plate(config, offset, [seed, index], design)
        measured, truth = measure_plate(config, plate, plan, seed * 101 + index, known, chain_map)
        found += len(measured)
        expected += len(known)
        measured_all.append(measured)
        known_all.append(truth)
    sigma, stacked = chain_sigma_mm(measured_all, known_all)
    known_stacked = np.vstack(known_all)
    joint = aligned_residuals(np.vstack(measured_all), known_stacked)
    bounds = np.cumsum([0] + [len(m) for m in measured_all])
    bias = tuple(tuple(float(v) for v in joint[a:b].mean(axis=0)) for a, b in zip(bounds[:-1], bounds[1:]))
    return ReferencePlateResult(sigma, bias, found, expected, known_stacked[:, :2], stacked)


CHAIN_MAP_SEED_BASE = 7919
"""Offset of the chain map's sweep seeds: its sweeps draw their random errors apart from the
reference check's and the calibration's (the robot's repeating field is the cell's, the same)."""


def measure_chain_map(config: SimConfig, plan: MeasurementPlan, seed: int = 1, repeats: int = 2,
                      design: ReferencePlateDesign = FIELD_PLATE, fit: ChainMapFit = ChainMapFit()) -> ChainMap:
    """Measure the chain map of ``plan``'s lines on the simulated cell ``config``.

    The certified plate ``design`` (one placement per position) is swept ``repeats`` times along
    every line of ``plan`` -- the calibration's programmed lines, on the same simulated robot (its
    repeating field is drawn from the cell's seed) -- each sweep's fiducials measured on the plate
    plane of that placement's first sweep (no plain sweeps: the map needs only in-plane centres),
    paired with the known centres and handed to :func:`chain_map.fit_chain_map`. Cell time:
    ``repeats * len(plan.passes)`` sweeps per placement.

    Parameters
    ----------
    config : SimConfig
        The simulated cell.
    plan : MeasurementPlan
        The lines; it must place profiles by pose.
    seed : int, default 1
        Seed of the map's plates and sweeps.
    repeats : int, default 2
        Sweeps per line and placement; at least 1.
    design : ReferencePlateDesign, default FIELD_PLATE
        The plate with known centres.
    fit : ChainMapFit, optional
        How the map is fitted.

    Returns
    -------
    ChainMap
        The fitted map.

    Raises
    ------
    ValueError
        When ``repeats`` is not a positive integer, the plan is not placed by pose (a map of the
        reported pose needs the pose), or too few centres are found.
    """
    as_integer_at_least(repeats, "repeats", 1)
    if not plan.placed_by_pose:
        raise ValueError("a chain map maps the robot's reported pose: the plan must place profiles by pose")
    scanner = config.make_scanner()
    mounting = RigidTransform(config.scanner_to_gls[:3, :3].copy(), config.scanner_to_gls[:3, 3].copy())
    sweeps = []
    for index, offset in enumerate(design.positions_mm):
        plate, known_gls = _reference_plate(config, offset, [CHAIN_MAP_SEED_BASE + seed, index], design)
        # the known centres where the CAD mounting puts them in B: a rigid motion of the plate's own
        # frame (B is mirrored against the gls frame, the plate's frame is not)
        known_plate = ((known_gls - mounting.translation) @ mounting.rotation)[:, :2]
        pose = None
        for repeat in range(repeats):
            for number, item in enumerate(plan.passes):
                data = scanner.sweep_data(plate, config.sweep_length_mm, step_mm=plan.marked_step_mm,
                                          seed=(CHAIN_MAP_SEED_BASE + seed) * 1009 + 97 * index
                                          + len(plan.passes) * repeat + number,
                                          direction=item.direction, orientation_deg=item.orientation_deg)
                xyz = data.placed_by_pose()
                if pose is None:
                    pose = plate_plane(xyz)
                found = measure_fiducials(xyz, data.intensity, pose, ring_radii_mm=RING_RADII_MM,
                                          expected_count=len(known_gls))
                if len(found.centres) < 3:
                    raise ValueError(f"chain map sweep {item.label}: found {len(found.centres)} of "
                                     f"{len(known_gls)} reference centres")
                pairing = pair_with_targets(mounting.apply(found.centres), known_gls)
                sweeps.append(ReferenceSweep(item.label, index, known_plate[pairing.target_index],
                                             found.centres[pairing.measured_index, :2]))
    reference = (f"simulated reference plate, {design.label}; preset {config.measurement_preset}, "
                 f"cell seed {config.seed}, map seed {seed}")
    return fit_chain_map(sweeps, reference, fit)


def chain_check(result: ReferencePlateResult, plan: MeasurementPlan, config: SimConfig, seed: int,
                design: ReferencePlateDesign = PAPER_PLATE, chain_map: ChainMap | None = None) -> ChainCheck:
    """Return the reference check of ``plan`` as the calibration manager reads it.

    It is the ``result`` of :func:`reference_plate_check` on ``design``, with ``chain_map`` applied,
    in the form the manager reads (``stated_accuracy``): what the cell may state its accuracy from.

    Parameters
    ----------
    result : ReferencePlateResult
        The check's result.
    plan : MeasurementPlan
        The plan it was measured with.
    config : SimConfig
        The simulated cell (its preset and seed are named).
    seed : int
        The check's seed (named).
    design : ReferencePlateDesign, default PAPER_PLATE
        The plate with known centres.
    chain_map : ChainMap, optional
        The chain map applied while measuring it.

    Returns
    -------
    ChainCheck
        The validated check.

    Raises
    ------
    ValueError
        If the result does not make a valid :class:`ChainCheck` (e.g. fewer than 3 centres found).
    """
    return ChainCheck(sigma_mm=result.sigma_mm, plan=plan.label, placement=plan.placement,
                      reference=(f"simulated reference plate, {design.label}; preset "
                                 f"{config.measurement_preset}, cell seed {config.seed}, check seed {seed}"),
                      centres=result.found, chain_map=chain_map_identity(chain_map),
                      extent_mm=None if result.known_xy_mm is None
                      else centres_extent_mm(result.known_xy_mm))
