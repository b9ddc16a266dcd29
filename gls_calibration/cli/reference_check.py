"""``gls-reference-check``: a real cell's reference check from a bag of a plate with certified centres.

Usage: ``gls-reference-check --bag BAG --certified CENTRES.csv --reference TEXT --out check.yaml``.

The stated accuracy of a calibration (``calibration/stated_accuracy.py``) adds a check of the
measurement chain against a plate with known centres. This tool measures that check from a rosbag2
recording of such a plate, scanned exactly as the calibration scans its marked plate: the plain
sweeps (``--plain-sweeps``), then one sweep per pass of the sweep plan (``--sweep-plan``), in that
order; stand-stills in the bag are skipped. The sweeps are assembled as ``gls-measure --bag`` and
``gls-train --bag`` assemble them (profiles placed by the robot's reported pose, the galvo frame from
the bag's ``/tf_static``), measured and combined by the calibration's own code
(``calibration/reference_check.py``), paired with the certified centres, aligned by the best 2-D
rigid motion, and the per-axis standard deviation (k = 1) is written as a reference check file
(``reference_check_file`` of the calibration manager).

``--certified``: a CSV with a header naming ``x`` and ``y`` (and optionally ``z``), mm, one row per
certified centre, in the galvo frame where the plate nominally lies (the plate's own certified
coordinates turned and shifted to its nominal place: pairing searches rotations up to 15 deg and any
shift, the exact rigid motion is removed anyway). The plate must carry the calibration's double rings
(``fiducials.targets.RING_RADII_MM``): e.g. a plate marked once and measured on a coordinate measuring
machine. ``--chain-map FILE``: the chain map the calibrations will run with, removed from every sweep
as they remove it (its identity is written into the check). ``--residuals FILE.csv``: each paired
centre's residual after the best rigid motion (``x_mm,y_mm,dx_mm,dy_mm``), where the chain errs.

The check records the extent of the certified centres it paired (``extent_mm``): a calibration whose
grid reaches more than ``stated_accuracy.EXTENT_TOLERANCE_MM`` beyond it states no accuracy from it, and
the tool warns when the certified centres end short of the grid of ``config/gls.yaml``.

Exit 0 with the file written; 2 on bad input, nothing written.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import math
from pathlib import Path
import sys

import numpy as np

from gls_calibration.calibration.procedure import CalibrationError
from gls_calibration.calibration.reference_check import (certified_reach, chain_check, measure_reference_plate,
                                                         read_certified_centres)
from gls_calibration.calibration.stated_accuracy import ChainCheck, save_chain_check
from gls_calibration.cli.train_bag import recording_settings, require_recorded_length
from gls_calibration.common.files import atomic_write_text, require_regular_output
from gls_calibration.registration.chain_map import load_chain_map
from gls_calibration.registration.rigid import RigidTransform
from gls_calibration.registration.sweep_plan import plan_label
from gls_calibration.scan.bag_io import BagLayout, read_recording

LOW_PAIRED_FRACTION = 0.9
"""Below this share of the certified centres paired, the tool warns (the figure still stands for
the centres it has)."""


def residuals_csv(known_mm: np.ndarray, residuals_mm: np.ndarray) -> str:
    """Return the CSV text of each paired certified centre and its residual after the best rigid motion.

    Parameters
    ----------
    known_mm : numpy.ndarray, shape (N, 2 or 3)
        The certified centres that were paired, mm.
    residuals_mm : numpy.ndarray, shape (N, 2)
        Measured minus certified after the alignment, mm.

    Returns
    -------
    str
        Header ``x_mm,y_mm,dx_mm,dy_mm`` and one row per centre.
    """
    rows = (f"{x:.6f},{y:.6f},{dx:.6f},{dy:.6f}\n" for (x, y), (dx, dy) in zip(known_mm[:, :2], residuals_mm))
    return "x_mm,y_mm,dx_mm,dy_mm\n" + "".join(rows)


def measure_check(args: argparse.Namespace) -> tuple[ChainCheck, int, str, str]:
    """Measure the reference check the arguments describe.

    Return it, the number of certified centres, the residuals' CSV text and whether the centres reach the grid.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    check : ChainCheck
        The validated check.
    certified : int
        Certified centres in the CSV.
    residuals : str
        The paired centres and their residuals (:func:`residuals_csv`).
    short : str
        Why the certified centres cannot check the calibration grid of ``config/gls.yaml``
        (``reference_check.certified_reach``); empty when they can.

    Raises
    ------
    ValueError
        On bad input (names the problem).
    """
    require_regular_output(args.out)
    if args.residuals is not None:
        require_regular_output(args.residuals)
        if args.residuals.resolve() == args.out.resolve():
            raise ValueError("--residuals and --out name the same file")
    if not args.reference.strip():
        raise ValueError("--reference must name the plate and its certificate")
    known = read_certified_centres(args.certified)
    recording = recording_settings(None, None, args.sweep_plan, args.plain_sweeps)
    plan, plain_sweeps = recording.sweep_plan, recording.plain_sweeps
    chain_map = load_chain_map(args.chain_map) if args.chain_map is not None else None
    given = {"scan_topic": args.scan_topic, "base_frame": args.base_frame, "sensor_frame": args.sensor_frame}
    layout = BagLayout(**{name: value for name, value in given.items() if value is not None})
    motions, gls_in_base = read_recording(args.bag, layout)
    require_recorded_length(motions, recording.cell_time.sweep_length_mm)
    sweeps = [sweep for sweep in motions if not sweep.standstill]
    wanted = plain_sweeps + len(plan)
    if len(sweeps) != wanted:
        raise ValueError(f"{args.bag}: {len(sweeps)} sweep(s) (stand-stills skipped); the check takes {wanted} "
                         f"({plain_sweeps} plain, then the {len(plan)} pass(es) of {plan_label(plan)})")
    scanner_to_gls = np.linalg.inv(gls_in_base)
    settings = replace(recording, profiles_placed_by_pose=True, chain_map=chain_map,
                       scanner_to_gls=RigidTransform(scanner_to_gls[:3, :3], scanner_to_gls[:3, 3]))
    plain = (sweep.xyz_mm for sweep in sweeps[:plain_sweeps])
    passes = ((sweep.xyz_mm, sweep.intensity) for sweep in sweeps[plain_sweeps:])
    try:
        measured, paired = measure_reference_plate(plain, passes, settings, known)
    except CalibrationError as error:
        raise ValueError(str(error)) from None
    check, residuals = chain_check(measured, paired, settings, args.reference)
    return check, len(known), residuals_csv(paired, residuals), certified_reach(known, settings)


def main(argv: list[str] | None = None) -> int:
    """Exit 0 with the check written, 2 on bad input (nothing written then)."""
    parser = argparse.ArgumentParser(prog="gls-reference-check", description=__doc__.splitlines()[0])
    parser.add_argument("--bag", type=Path, required=True, help="rosbag2 folder: plain sweeps, then the plan's passes")
    parser.add_argument("--certified", type=Path, required=True, help="CSV of the certified centres (x, y[, z], mm)")
    parser.add_argument("--reference", required=True, help="names the plate and its certificate")
    parser.add_argument("--out", type=Path, required=True, help="the reference check file to write (YAML)")
    parser.add_argument("--sweep-plan", default=None, help="the calibration's sweep.plan (default: config/gls.yaml's)")
    parser.add_argument("--plain-sweeps", type=int, default=None,
                        help="plain sweeps at the start of the bag (default: sweep.plain_repeats of config/gls.yaml)")
    parser.add_argument("--chain-map", type=Path, default=None, help="the chain map file the calibrations use")
    parser.add_argument("--residuals", type=Path, default=None,
                        help="also write each paired centre's residual after the best rigid motion (CSV, mm)")
    defaults = BagLayout()
    parser.add_argument("--scan-topic", help=f"the profiles' topic (default {defaults.scan_topic})")
    parser.add_argument("--base-frame", help=f"the frame the sweeps are placed in (default {defaults.base_frame})")
    parser.add_argument("--sensor-frame", help=f"the profiles' frame (default {defaults.sensor_frame})")
    args = parser.parse_args(argv)
    if args.plain_sweeps is not None and args.plain_sweeps < 0:
        parser.error(f"--plain-sweeps must be 0 or more, got {args.plain_sweeps}")
    try:
        check, certified, residuals, short = measure_check(args)
        if args.residuals is not None:
            atomic_write_text(args.residuals, residuals)
        save_chain_check(args.out, check)
    except (ValueError, OSError) as error:
        print(f"gls-reference-check: {getattr(error, 'strerror', None) or error}", file=sys.stderr)
        return 2
    print(f"reference check: sigma x {check.sigma_mm[0]:.4f} mm, y {check.sigma_mm[1]:.4f} mm (k = 1, 2-D "
          f"{math.hypot(*check.sigma_mm):.4f} mm) from {check.centres} of {certified} certified centres; "
          f"plan {check.plan}, chain map {check.chain_map}; written to {args.out}")
    if check.centres < LOW_PAIRED_FRACTION * certified:
        print(f"gls-reference-check: only {check.centres} of {certified} certified centres were measured and "
              "paired: check the plate's placement and the scan", file=sys.stderr)
    if short:
        print(f"gls-reference-check: {short}", file=sys.stderr)
    return 0
