"""What the cell may claim: a calibration's accuracy stated against an independent reference.

The validation plate is marked through the new calibration and measured by the same chain (robot
lines, scanner, plate pose) that measured the training plate. Errors of that chain that repeat --
the robot's reported-versus-true pose along the same programmed lines, the scanner's fixed shapes --
were learned into the calibration and are measured again, with the same sign, on the validation
plate: they cancel in the MEASURED figure although the marks land off by them. The measured figure
is therefore *self-consistency*: it cannot see the chain's repeating error.

A reference check sees it: a plate with known centres (a certified grid plate in a real cell, the
simulated reference plate in simulation) measured with the calibration's own plan, its centres
compared with the known ones after the best rigid motion. Its per-axis standard deviation
``sigma_x, sigma_y`` (k = 1) bounds what the chain adds to every measured centre, repeating part
included. The stated accuracy adds the two:

    stated_rms = measured_rms + sqrt(sigma_x^2 + sigma_y^2)

The TRUE error after calibration is the chain's error that the calibration learned (what the check
measures, up to the check's own random part) plus the difference between the random parts of the
calibration's and the check's measurements plus the model's error between fiducials; the last two
are of the kind the measured figure holds. An RMS of a sum is at most the sum of the RMS values
(Minkowski), so the sum bounds the truth without assuming the parts independent. The quadrature sum
``sqrt(measured^2 + sigma_x^2 + sigma_y^2)``, which does assume it, fell below the TRUE error on one
of nine simulated runs (``careful`` seed 3: 0.0233 against 0.0238 mm) and was within 1 % of it on
another: too close for a figure users build on. The price: the sum reached 2.25 times the truth
without a chain map and 4.1 times with one in simulation (``docs/method-and-results.md``), where the
validation plate's own random measurement error, which the truth does not hold, makes up most of the
measured figure. Where the reference check is missing or was made with another plan, nothing
independent is known: the cell states no figure (NaN) and labels its measured figure
self-consistency. The same holds for a check whose known centres do not reach the calibrated
targets' outermost ones (to ``EXTENT_TOLERANCE_MM``): the chain's repeating error grows towards the
ends of the robot's lines, and a 180 mm check plate under the 190 mm grid showed 57 % of it on one
simulated cell (``reference_plate.field_plate``). Reaching the targets' extent is necessary, not
sufficient: the bounding boxes are compared, not the coverage.

A reference check is a small YAML file (:func:`save_chain_check`, :func:`load_chain_check`)::

    reference_check:
      sigma_mm: [0.031, 0.048]          # per axis (gls x, y), k = 1, after the best rigid motion
      plan: "0+,0-,90+,90-"             # the passes it was measured with (sweep_plan.parse_plan)
      placement: pose                   # profiles placed by the robot's reported pose, or by time
      reference: "simulated reference plate, 13 x 11 rings at 10 mm, 3 positions"
      centres: 429                      # known centres compared
      chain_map: none                   # the chain map its sweeps were corrected with (ChainMap.identity);
                                        # optional, "none" when left out
      extent_mm: [-95.0, 95.0, -95.0, 95.0]   # x min, x max, y min, y max of the known centres compared
                                        # (gls frame); null or left out: not recorded, no figure is stated

Example
-------
>>> check = ChainCheck(sigma_mm=(0.03, 0.04), plan="0+,90+", placement="pose", reference="plate A", centres=143,
...                    extent_mm=(-95.0, 95.0, -95.0, 95.0))
>>> grid = np.array([[-95.0, -95.0], [95.0, 95.0]])
>>> stated = stated_accuracy(0.02, check, plan="0+,90+", placement="pose", targets_xy_mm=grid)
>>> round(stated.rms_mm, 4), stated.basis
(0.07, 'reference check')
>>> stated_accuracy(0.02, check, plan="0+,90+", placement="pose", targets_xy_mm=1.1 * grid).basis
'self-consistency'
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np
import yaml

from gls_calibration.common.config_files import read_config_file, require_exact_keys
from gls_calibration.common.files import atomic_write_text
from gls_calibration.registration.chain_map import NO_CHAIN_MAP
from gls_calibration.registration.sweep_plan import parse_plan, plan_label

PLACEMENTS = ("pose", "time")
REFERENCE_BASIS = "reference check"
SELF_CONSISTENCY = "self-consistency"

EXTENT_TOLERANCE_MM = 2.5
"""How far inside the calibrated targets' outermost centres a check's centres may end, mm: enough for
a plate marked through the uncalibrated head (its rings up to ~2.1 mm off their targets on
``paper_like``) and laid in the fixture by hand; not for a plate one pitch (~10.6 mm) smaller."""


def placement_name(placed_by_pose: bool) -> str:
    """Return how profiles were placed as a check and a calibration name it.

    Parameters
    ----------
    placed_by_pose : bool
        Profiles placed by the robot's reported pose (else by time).

    Returns
    -------
    str
        ``"pose"`` or ``"time"`` (one of ``PLACEMENTS``).
    """
    return PLACEMENTS[0] if placed_by_pose else PLACEMENTS[1]


@dataclass(frozen=True)
class ChainCheck:
    """An independent check of the measurement chain against known centres (mm, k = 1).

    Parameters
    ----------
    sigma_mm : tuple of 2 float
        Per-axis standard uncertainty of the chain, mm; positive.
    plan : str
        The sweep plan it was measured with (stored as ``plan_label`` writes it).
    placement : str
        How profiles were placed, one of ``PLACEMENTS``.
    reference : str
        Names the plate with known centres it was measured on.
    centres : int
        Centres compared; at least 3.
    chain_map : str, default NO_CHAIN_MAP
        ``ChainMap.identity`` of the map applied while measuring it.
    extent_mm : tuple of 4 float, optional
        ``(x_min, x_max, y_min, y_max)`` of the known centres compared (gls frame, mm,
        :func:`centres_extent_mm`); None: not recorded, and then the check supports no figure.

    Raises
    ------
    ValueError
        On the first bad field.
    """

    sigma_mm: tuple[float, float]
    plan: str
    placement: str
    reference: str
    centres: int
    chain_map: str = NO_CHAIN_MAP     # ``ChainMap.identity`` of the map applied while measuring it
    extent_mm: Optional[tuple[float, float, float, float]] = None

    def __post_init__(self) -> None:
        """Validate the fields and store them normalised (ValueError on the first bad one)."""
        sigma = _finite_numbers(self.sigma_mm, 2)
        if sigma is None or min(sigma) <= 0.0:
            raise ValueError(f"reference_check.sigma_mm must be two positive finite numbers, got {self.sigma_mm!r}")
        object.__setattr__(self, "sigma_mm", sigma)
        if not isinstance(self.plan, str):
            raise ValueError(f"reference_check.plan must be a sweep plan such as 0+,0-,90+,90-, got {self.plan!r}")
        try:
            object.__setattr__(self, "plan", plan_label(parse_plan(self.plan)))
        except ValueError as error:
            raise ValueError(f"reference_check.plan: {error}") from None
        if self.placement not in PLACEMENTS:
            raise ValueError(f"reference_check.placement must be one of {', '.join(PLACEMENTS)}, "
                             f"got {self.placement!r}")
        if not isinstance(self.reference, str) or not self.reference.strip():
            raise ValueError("reference_check.reference must name the plate with known centres it was measured on")
        if isinstance(self.centres, bool) or not isinstance(self.centres, int) or self.centres < 3:
            raise ValueError(f"reference_check.centres must be an integer of at least 3, got {self.centres!r}")
        if not isinstance(self.chain_map, str) or not self.chain_map.strip():
            raise ValueError(f"reference_check.chain_map must be {NO_CHAIN_MAP!r} or a chain map's identity "
                             f"(sha256:...), got {self.chain_map!r}")
        if self.extent_mm is not None:
            extent = _finite_numbers(self.extent_mm, 4)
            if extent is None or not (extent[0] < extent[1] and extent[2] < extent[3]):
                raise ValueError(f"reference_check.extent_mm must be [x_min, x_max, y_min, y_max] in mm with "
                                 f"x_min < x_max and y_min < y_max, got {self.extent_mm!r}")
            object.__setattr__(self, "extent_mm", extent)

    @property
    def rms_2d_mm(self) -> float:
        """Return the chain's 2-D RMS error at one centre, sqrt(sigma_x^2 + sigma_y^2)."""
        return math.hypot(*self.sigma_mm)

    def to_dict(self) -> dict:
        """Plain form of the reference check for summary.json and the check file."""
        return {"sigma_mm": list(self.sigma_mm), "plan": self.plan, "placement": self.placement,
                "reference": self.reference, "centres": self.centres, "chain_map": self.chain_map,
                "extent_mm": None if self.extent_mm is None else list(self.extent_mm)}


def centres_extent_mm(centres_mm: np.ndarray) -> tuple[float, float, float, float]:
    """Return ``(x_min, x_max, y_min, y_max)`` of centres (N, 2 or more columns), mm.

    Parameters
    ----------
    centres_mm : numpy.ndarray, shape (N, >= 2)
        Centres, mm; N at least 1, finite.

    Returns
    -------
    tuple of 4 float
        Their bounding box in x and y.

    Raises
    ------
    ValueError
        If there is no centre or a coordinate is not finite.
    """
    xy = np.asarray(centres_mm, dtype=float)
    if xy.ndim != 2 or xy.shape[0] < 1 or xy.shape[1] < 2 or not np.all(np.isfinite(xy[:, :2])):
        raise ValueError(f"centres must be (N, 2 or 3) finite, N at least 1, got shape {xy.shape}")
    return (float(xy[:, 0].min()), float(xy[:, 0].max()), float(xy[:, 1].min()), float(xy[:, 1].max()))


def sides_short_of(extent_mm: tuple[float, float, float, float],
                   needed_mm: tuple[float, float, float, float]) -> tuple[str, ...]:
    """Return the sides (``"x min"``, ...) where ``extent_mm`` ends more than ``EXTENT_TOLERANCE_MM`` short.

    Parameters
    ----------
    extent_mm, needed_mm : tuple of 4 float
        ``(x_min, x_max, y_min, y_max)`` reached and to be reached (:func:`centres_extent_mm`), mm.

    Returns
    -------
    tuple of str
        The sides short of ``needed_mm``; empty when it is reached.

    Examples
    --------
    >>> sides_short_of((-90.0, 90.0, -96.0, 96.0), (-95.0, 95.0, -95.0, 95.0))
    ('x min', 'x max')
    """
    sides = zip(("x min", "x max", "y min", "y max"), extent_mm, needed_mm, (-1.0, 1.0, -1.0, 1.0))
    return tuple(name for name, reached, needed, outward in sides if outward * (needed - reached) > EXTENT_TOLERANCE_MM)


def check_mismatch(check: ChainCheck, *, plan: str, placement: str, chain_map: str,
                   targets_xy_mm: np.ndarray) -> str:
    """Return why ``check`` does not describe the chain of a calibration, or ``""`` when it does.

    It describes it when it was measured with the same sweep plan, profile placement and chain map,
    and its known centres reach the calibrated targets' outermost ones to ``EXTENT_TOLERANCE_MM``.

    Parameters
    ----------
    check : ChainCheck
        The reference check.
    plan, placement, chain_map : str
        The calibration's sweep plan (any form ``parse_plan`` reads), placement and chain map identity.
    targets_xy_mm : numpy.ndarray, shape (N, >= 2)
        The calibration's targets (gls frame, mm).

    Returns
    -------
    str
        The reason, one sentence; empty when the check applies.

    Raises
    ------
    ValueError
        If ``plan`` is not a sweep plan or ``targets_xy_mm`` holds no finite centre.
    """
    targets = centres_extent_mm(targets_xy_mm)
    plan = plan_label(parse_plan(plan))
    if check.plan != plan or check.placement != placement:
        return (f"the reference check was measured with plan {check.plan} placed by {check.placement}, "
                f"the calibration with {plan} placed by {placement}: it does not describe this chain")
    if check.chain_map != chain_map:
        return (f"the reference check was measured with chain map {check.chain_map}, the calibration "
                f"with {chain_map}: it does not describe this chain")
    if check.extent_mm is None:
        return ("the reference check does not record the area its known centres cover (a file written before "
                "extent_mm was kept): measure it again to state a figure")
    short = sides_short_of(check.extent_mm, targets)
    if short:
        return (f"the reference check's known centres span x {check.extent_mm[0]:.1f}..{check.extent_mm[1]:.1f}, "
                f"y {check.extent_mm[2]:.1f}..{check.extent_mm[3]:.1f} mm and end short of the calibrated targets "
                f"(x {targets[0]:.1f}..{targets[1]:.1f}, y {targets[2]:.1f}..{targets[3]:.1f} mm) at "
                f"{', '.join(short)}: the chain's error at the field's edge is not checked")
    return ""


def _finite_numbers(values: Any, count: int) -> Optional[tuple[float, ...]]:
    """Return ``values`` as ``count`` floats when it is a list or tuple of that many finite numbers, else None."""
    if not isinstance(values, (list, tuple)) or len(values) != count or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values):
        return None
    return tuple(float(v) for v in values)


def chain_check_from_mapping(document: Any) -> ChainCheck:
    """Return a :class:`ChainCheck` from the parsed file (``{reference_check: {...}}``); ValueError naming the key."""
    if not isinstance(document, Mapping) or not isinstance(document.get("reference_check"), Mapping):
        raise ValueError("a reference check file holds one mapping 'reference_check'")
    block = dict(document["reference_check"])
    block.setdefault("chain_map", NO_CHAIN_MAP)    # files written before chain maps existed
    block.setdefault("extent_mm", None)            # and before the extent was kept: then no figure
    keys = ("sigma_mm", "plan", "placement", "reference", "centres", "chain_map", "extent_mm")
    require_exact_keys(block, keys, "reference_check")
    return ChainCheck(**block)


def load_chain_check(path: str | Path) -> ChainCheck:
    """Read and validate a reference check file.

    Parameters
    ----------
    path : str or pathlib.Path
        The YAML file (one mapping ``reference_check``).

    Returns
    -------
    ChainCheck
        The validated check.

    Raises
    ------
    ValueError
        Naming the file and the key, for an unreadable file or YAML or a bad value.
    """
    return read_config_file(path, "reference check file", chain_check_from_mapping)


def save_chain_check(path: str | Path, check: ChainCheck) -> None:
    """Write ``check`` atomically as a reference check file.

    Parameters
    ----------
    path : str or pathlib.Path
        The YAML file to write.
    check : ChainCheck
        The check.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> check = ChainCheck((0.004, 0.005), "0+,0-", "pose", "certified plate 7", 49, extent_mm=(-96, 96, -96, 96))
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = pathlib.Path(folder) / "reference_check.yaml"
    ...     save_chain_check(path, check)
    ...     load_chain_check(path) == check
    True
    """
    atomic_write_text(path, yaml.safe_dump({"reference_check": check.to_dict()}, sort_keys=False))


@dataclass(frozen=True)
class StatedAccuracy:
    """The accuracy a user can rely on (2-D RMS, mm; NaN when no independent reference supports one)."""

    rms_mm: float
    basis: str            # REFERENCE_BASIS or SELF_CONSISTENCY
    explanation: str


def stated_accuracy(measured_rms_mm: float, check: Optional[ChainCheck], *, plan: str,
                    placement: str, targets_xy_mm: np.ndarray, chain_map: str = NO_CHAIN_MAP) -> StatedAccuracy:
    """Return the stated accuracy of a calibration validated at ``measured_rms_mm`` (2-D RMS, the same chain).

    Parameters
    ----------
    measured_rms_mm : float
        RMS of |delta| on the validation plate, measured by the cell (self-consistency).
    check : ChainCheck or None
        The reference check of the chain; None when the cell has none.
    plan, placement : str
        The sweep plan and profile placement the calibration ran with; a check made otherwise does
        not describe this chain.
    targets_xy_mm : numpy.ndarray, shape (N, >= 2)
        The calibration's targets (gls frame, mm): a check whose known centres end short of them
        does not check the field's edge (:func:`check_mismatch`).
    chain_map : str
        Identity of the chain map the calibration's sweeps were corrected with (``NO_CHAIN_MAP``:
        none); a check made with another map (or none) does not describe this chain either.

    Returns
    -------
    StatedAccuracy
        ``rms_mm = measured + sqrt(sigma_x^2 + sigma_y^2)`` on the reference check's basis, or NaN
        and the basis ``self-consistency`` with the reason.

    Raises
    ------
    ValueError
        When ``measured_rms_mm`` is negative or not finite, or ``targets_xy_mm`` holds no finite centre.
    """
    if isinstance(measured_rms_mm, bool) or not isinstance(measured_rms_mm, (int, float)) \
            or not math.isfinite(measured_rms_mm) or measured_rms_mm < 0.0:
        raise ValueError(f"measured_rms_mm must be a non-negative finite number, got {measured_rms_mm!r}")
    plan = plan_label(parse_plan(plan))
    if check is None:
        centres_extent_mm(targets_xy_mm)       # bad targets are refused with or without a check
        return StatedAccuracy(math.nan, SELF_CONSISTENCY,
                              "no reference check of the measurement chain: the measured figure is "
                              "self-consistency and cannot see errors of the chain that repeat")
    reason = check_mismatch(check, plan=plan, placement=placement, chain_map=chain_map, targets_xy_mm=targets_xy_mm)
    if reason:
        return StatedAccuracy(math.nan, SELF_CONSISTENCY, reason)
    rms = measured_rms_mm + check.rms_2d_mm
    return StatedAccuracy(rms, REFERENCE_BASIS,
                          f"validation {measured_rms_mm:.4f} mm RMS (self-consistency) plus the chain's "
                          f"{check.rms_2d_mm:.4f} mm ({check.sigma_mm[0]:.4f} / {check.sigma_mm[1]:.4f} mm per axis) "
                          f"against known centres "
                          f"({check.reference}, {check.centres} centres)")
