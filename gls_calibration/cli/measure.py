"""gls-measure: measure the ring fiducials of a plate scan offline, without the ROS cell.

Reads a cloud (``.npz`` with arrays x, y, z, intensity of equal shape in mm, 2-D organized or 1-D
unorganized, NaN for missing points; or ``.pcd`` / ``.ply`` through Open3D), estimates the plate
pose, measures the fiducials with the same core function as the fiducial_measurement node
(``fiducials.measure_fiducials``) and writes into DIR (created):

- ``centres.csv``: ``x,y,z,sigma_x_um,sigma_y_um,coverage,status``, one row per candidate
  (coordinates in the cloud's frame in mm, standard uncertainty at k = 1 in um, coverage 0-1,
  status ``ok`` or ``rejected:<reason>``); only the header when nothing was found;
- ``detections.png``: the plate image with accepted (green) and rejected (red, with the reason)
  detections drawn;
- ``summary.json``: counts, median/max uncertainty, coverage, plate pose, the cloud's units and time.

The cloud may be in millimetres or metres (most ROS and PCL exports): ``--units m|mm``, or, without
it, the unit in which the plate's extent holds the grid (``--size`` plus its rings) without
exceeding it more than ``MAX_EXTENT_RATIO`` times (``cloud_units``). Outputs are in mm either way.
Without ``--pixel`` the raster pixel of an unorganized cloud comes from its own point spacing.

With ``--bag BAG`` (a rosbag2 recording, see :mod:`gls_calibration.scan.bag_io`) every sweep is assembled
in the base frame and measured the same way, into ``DIR/sweep_NN/`` (NN the motion's number in the
bag; stand-stills, one line of profiles each, are skipped), with ``DIR/sweeps.json``.

Exit 0 on success (also when no fiducial is found), 2 on bad input (unreadable file, missing or
mismatched arrays, a cloud whose extent cannot hold the grid, no plane, 1 to 3 fiducials found: too
few to use); nothing is written then.
"""
from __future__ import annotations

import argparse
from collections import Counter
import json
from pathlib import Path
import sys
import time

import cv2
import numpy as np

from gls_calibration.common.files import atomic_write_bytes, atomic_write_text
from gls_calibration.fiducials.measure import STATUS_OK, FiducialMeasurement, measure_fiducials
from gls_calibration.fiducials.targets import RING_RADII_MM
from gls_calibration.scan.bag_io import BagLayout, read_sweeps
from gls_calibration.scan.plate_pose import PlatePose, estimate_plate_pose

CSV_HEADER = "x,y,z,sigma_x_um,sigma_y_um,coverage,status"
NPZ_ARRAYS = ("x", "y", "z", "intensity")
MIN_FOUND = 4
"""Fewer accepted fiducials than this (but more than none) cannot support a calibration: bad input."""
MM_PER_UNIT = {"mm": 1.0, "m": 1000.0}
"""Millimetres per unit of the cloud's coordinates, by ``--units``."""
MAX_EXTENT_RATIO = 10.0
"""Without ``--units``, a unit is taken when the plate's extent in it is at least the grid's and at
most this many times it: the two units differ 1000-fold, so any ratio well below that tells them
apart, and 10 leaves room for a scan much wider than its grid."""
IMAGE_MAX_SIDE_PX = 2400
"""The picture is binned coarser than ``--pixel`` when the plate would be larger than this."""


def _positive_float(text: str) -> float:
    value = float(text)
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _rings(text: str) -> tuple[float, ...]:
    try:
        radii = tuple(float(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be radii in mm separated by commas, got {text!r}") from None
    if len(radii) < 1 or not all(np.isfinite(r) and r > 0 for r in radii) or len(set(radii)) != len(radii):
        raise argparse.ArgumentTypeError(f"must be distinct positive radii in mm, got {text!r}")
    return radii


def load_cloud(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read xyz (H, W, 3) or (N, 3) and intensity of a cloud file; ValueError names the problem."""
    suffix = path.suffix.lower()
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                names = list(data.files)
                arrays = {name: np.asarray(data[name]) for name in NPZ_ARRAYS if name in names}
        except Exception as error:      # zip, pickle and OS errors: the file is not a usable npz
            raise ValueError(f"{path}: unreadable npz file ({error})") from None
        missing = [name for name in NPZ_ARRAYS if name not in arrays]
        if missing:
            raise ValueError(f"{path}: missing array(s) {', '.join(missing)} (has: {', '.join(names) or 'none'})")
        shapes = {name: array.shape for name, array in arrays.items()}
        if len(set(shapes.values())) != 1:
            raise ValueError(f"{path}: arrays x, y, z, intensity must have one shape, got "
                             + ", ".join(f"{name} {shape}" for name, shape in shapes.items()))
        shape = shapes["x"]
        if len(shape) not in (1, 2) or 0 in shape:
            raise ValueError(f"{path}: arrays must be 1-D (unorganized) or 2-D (organized) and not empty, "
                             f"got shape {shape}")
        try:
            xyz = np.stack([arrays[name].astype(float) for name in ("x", "y", "z")], axis=-1)
            intensity = arrays["intensity"].astype(float)
        except (TypeError, ValueError):
            raise ValueError(f"{path}: arrays must be numeric") from None
        return xyz, intensity
    if suffix in (".pcd", ".ply"):
        import open3d as o3d

        cloud = o3d.t.io.read_point_cloud(str(path))
        if "positions" not in cloud.point or len(cloud.point["positions"]) == 0:
            raise ValueError(f"{path}: unreadable or empty point cloud")
        xyz = cloud.point["positions"].numpy().astype(float).reshape(-1, 3)
        if "intensity" in cloud.point:
            intensity = cloud.point["intensity"].numpy().astype(float).reshape(-1)
        elif "colors" in cloud.point:
            intensity = cloud.point["colors"].numpy().astype(float).reshape(-1, 3).mean(axis=1)
        else:
            raise ValueError(f"{path}: the cloud has no intensity (or colour) field")
        return xyz, intensity
    raise ValueError(f"{path}: unsupported file type {suffix!r} (use .npz, .pcd or .ply)")


def plate_extent(xyz: np.ndarray) -> tuple[float, float]:
    """Return the sides (short, long) of the cloud's minimum-area rectangle on its best-fit plane.

    Sides (short, long) of the minimum-area rectangle holding the cloud's points on their best-fit
    plane, in the cloud's own units (no unit is assumed: the plane is the points' principal one).
    """
    points = xyz.reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) < 3:
        raise ValueError("the cloud has fewer than 3 finite points")
    sample = points[::max(1, len(points) // 100_000)]
    centred = sample - sample.mean(axis=0)
    axes = np.linalg.svd(centred, full_matrices=False)[2][:2]
    in_plane = (centred @ axes.T).astype(np.float32)
    sides = sorted(float(side) for side in cv2.minAreaRect(in_plane)[1])
    return sides[0], sides[1]


def cloud_units(extent: tuple[float, float], units: str | None, grid: int, size_mm: float,
                ring_radius_mm: float) -> str:
    """Return the cloud's unit (``mm`` or ``m``): ``units`` when given, else the one that fits.

    The cloud's unit (``mm`` or ``m``): ``units`` when given, else the one in which ``extent`` (short,
    long side in the cloud's units) holds the grid without exceeding it ``MAX_EXTENT_RATIO`` times.
    ValueError naming both sizes when the extent cannot hold the grid. A 1x1 grid is one fiducial:
    its centres span nothing, whatever ``size_mm`` says.
    """
    centres_span_mm = size_mm if grid >= 2 else 0.0
    required_mm = centres_span_mm + 2 * ring_radius_mm
    if units is None:
        fitting = [unit for unit, scale in MM_PER_UNIT.items()
                   if required_mm <= extent[0] * scale and extent[1] * scale <= MAX_EXTENT_RATIO * required_mm]
        units = fitting[0] if fitting else "mm"
    scale = MM_PER_UNIT[units]
    if extent[0] * scale < required_mm:
        raise ValueError(f"cloud extent {extent[0] * scale:.4g} x {extent[1] * scale:.4g} mm (read as {units}) "
                         f"cannot hold the {grid}x{grid} grid: it needs {required_mm:.4g} x {required_mm:.4g} mm "
                         f"({'--size ' + format(size_mm, 'g') + ' mm' if grid >= 2 else 'one fiducial'} plus rings of "
                         f"{ring_radius_mm:g} mm); check --size and --units")
    return units


def csv_text(measurement: FiducialMeasurement) -> str:
    """centres.csv: accepted candidates first, then the rejected ones."""
    lines = [CSV_HEADER]
    for centre, sigma, coverage in zip(measurement.centres, measurement.sigma_xy_mm, measurement.coverage):
        lines.append(f"{centre[0]:.6f},{centre[1]:.6f},{centre[2]:.6f},{sigma[0] * 1000:.3f},"
                     f"{sigma[1] * 1000:.3f},{coverage:.3f},{STATUS_OK}")
    for centre, sigma, coverage, reason in zip(measurement.rejected_centres, measurement.rejected_sigma_xy_mm,
                                               measurement.rejected_coverage, measurement.rejected_reasons):
        lines.append(f"{centre[0]:.6f},{centre[1]:.6f},{centre[2]:.6f},{sigma[0] * 1000:.3f},"
                     f"{sigma[1] * 1000:.3f},{coverage:.3f},rejected:{reason}")
    return "\n".join(lines) + "\n"


def detections_png(xyz: np.ndarray, intensity: np.ndarray, pose: PlatePose, measurement: FiducialMeasurement,
                   pixel_mm: float, ring_radius_mm: float) -> bytes:
    """Plate image (mean intensity per pixel on the plate plane) with the detections drawn."""
    points = xyz.reshape(-1, 3)
    values = intensity.reshape(-1)
    keep = np.isfinite(points).all(axis=1) & np.isfinite(values)
    uv = pose.to_plane(points[keep])
    low = uv.min(axis=0)
    extent = uv.max(axis=0) - low
    pixel = max(pixel_mm, float(extent.max()) / IMAGE_MAX_SIDE_PX)
    cols, rows = (int(v) + 1 for v in extent / pixel)
    index = np.floor((uv - low) / pixel).astype(int)
    flat = index[:, 1] * cols + index[:, 0]
    sums = np.bincount(flat, weights=values[keep], minlength=rows * cols)
    counts = np.bincount(flat, minlength=rows * cols)
    image = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan).reshape(rows, cols)
    finite = image[np.isfinite(image)]
    lo, hi = np.percentile(finite, (0.5, 99.5)) if finite.size else (0.0, 1.0)
    gray = np.clip((np.nan_to_num(image, nan=lo) - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)
    picture = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    radius_px = max(int(round(ring_radius_mm * 1.3 / pixel)), 3)
    thickness = max(1, radius_px // 12)
    font_scale = max(0.3, radius_px / 40)

    def draw(centres, colour, labels):
        if len(centres) == 0:
            return
        at = (pose.to_plane(np.asarray(centres).reshape(-1, 3)) - low) / pixel
        for (col, row), label in zip(at, labels):
            centre = (int(round(col)), int(round(row)))
            cv2.circle(picture, centre, radius_px, colour, thickness, cv2.LINE_AA)
            cv2.drawMarker(picture, centre, colour, cv2.MARKER_CROSS, radius_px // 2, thickness)
            if label:
                cv2.putText(picture, label, (centre[0] - radius_px, centre[1] - radius_px - 2),
                            cv2.FONT_HERSHEY_SIMPLEX, font_scale, colour, thickness, cv2.LINE_AA)

    draw(measurement.centres, (0, 200, 0), [""] * len(measurement.centres))
    draw(measurement.rejected_centres, (0, 0, 255), list(measurement.rejected_reasons))
    ok, encoded = cv2.imencode(".png", picture)
    if not ok:
        raise ValueError("could not encode detections.png")
    return encoded.tobytes()


def summary(measurement: FiducialMeasurement, pose: PlatePose, args, seconds: float, source: str,
            units: str) -> dict:
    """summary.json content."""
    sigma_um = np.asarray(measurement.sigma_xy_mm).reshape(-1, 2) * 1000

    def stats(values):
        return {"median": float(np.median(values)), "max": float(np.max(values))} if len(values) else None

    expected = args.grid**2
    return {
        "cloud": source,
        "grid": {"per_side": args.grid, "size_mm": args.size, "expected": expected},
        "rings_mm": list(args.rings),
        "candidates": len(measurement.centres) + int(measurement.rejected),
        "accepted": len(measurement.centres),
        "rejected": int(measurement.rejected),
        "rejected_by_reason": dict(Counter(measurement.rejected_reasons)),
        "missing": measurement.missing,
        "extra": measurement.extra,
        "sigma_x_um": stats(sigma_um[:, 0]),
        "sigma_y_um": stats(sigma_um[:, 1]),
        "coverage": ({"median": float(np.median(measurement.coverage)), "min": float(np.min(measurement.coverage))}
                     if len(measurement.coverage) else None),
        "plate_pose": {"normal": [float(v) for v in pose.normal], "centre_mm": [float(v) for v in pose.centre],
                       "flatness_rms_mm": float(pose.flatness_rms_mm)},
        "image_shape": list(measurement.image_shape),
        "pixel_pitch_mm": [float(v) for v in measurement.pixel_pitch_mm],
        "pixel_from": "--pixel" if args.pixel is not None else "point spacing",
        "cloud_units": units,
        "time_s": round(seconds, 3),
    }


def measure_cloud(xyz: np.ndarray, intensity: np.ndarray, args) -> tuple[PlatePose, FiducialMeasurement, float]:
    """Measure the plate pose and fiducials of one cloud (mm) and the seconds it took.

    Plate pose and fiducials of one cloud (mm) as the tool measures them, and the seconds it took;
    ValueError for no plane or 1 to 3 fiducials (too few to use).
    """
    start = time.perf_counter()
    pose = estimate_plate_pose(xyz)
    measurement = measure_fiducials(xyz, intensity, pose, ring_radii_mm=args.rings, pixel_size_mm=args.pixel,
                                    expected_count=args.grid**2, marks_darker=None, allow_empty=True)
    seconds = time.perf_counter() - start
    found = len(measurement.centres)
    if 0 < found < MIN_FOUND:
        raise ValueError(f"only {found} fiducial(s) found; at least {MIN_FOUND} are needed "
                         f"(grid {args.grid}x{args.grid})")
    return pose, measurement, seconds


def _outputs(xyz, intensity, args, source: str, units: str) -> tuple[dict[str, str], bytes, FiducialMeasurement,
                                                                     float]:
    """Return the texts and picture of one cloud's results (``xyz`` in mm, read from ``units``; nothing written)."""
    pose, measurement, seconds = measure_cloud(xyz, intensity, args)
    texts = {"centres.csv": csv_text(measurement),
             "summary.json": json.dumps(summary(measurement, pose, args, seconds, source, units), indent=2) + "\n"}
    picture = detections_png(xyz, intensity, pose, measurement, max(measurement.pixel_pitch_mm), max(args.rings))
    return texts, picture, measurement, seconds


def _bag_outputs(args) -> dict[str, tuple[dict[str, str], bytes, FiducialMeasurement, float]]:
    """Results of every sweep of ``args.bag`` by sub-folder name (``sweep_01``, ...)."""
    layout = BagLayout(**{name: value for name, value in (("scan_topic", args.scan_topic),
                                                          ("base_frame", args.base_frame),
                                                          ("sensor_frame", args.sensor_frame)) if value is not None})
    sweeps = read_sweeps(args.bag, layout)
    width = max(2, len(str(len(sweeps))))
    results = {}
    for number, sweep in enumerate(sweeps, 1):
        try:
            if sweep.standstill:    # profiles of one line (the plate height at marking): no fiducials to measure
                continue
            # bag_io reads the standard clouds in metres (REP 103) and gives millimetres
            results[f"sweep_{number:0{width}d}"] = _outputs(sweep.xyz_mm, sweep.intensity, args,
                                                            f"{args.bag} sweep {number}", "m")
        except ValueError as error:
            raise ValueError(f"{args.bag}: sweep {number}: {error}") from None
    return results


def main(argv: list[str] | None = None) -> int:
    """Exit 0 on success, 2 on bad input (nothing written then)."""
    parser = argparse.ArgumentParser(prog="gls-measure", description=__doc__.splitlines()[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--cloud", type=Path, help=".npz (x, y, z, intensity), .pcd or .ply")
    source.add_argument("--bag", type=Path, help="rosbag2 folder (SQLite3 or MCAP): every sweep measured")
    parser.add_argument("--grid", type=_positive_int, required=True, help="fiducials per side of the grid")
    parser.add_argument("--size", type=_positive_float, required=True, help="grid span, first to last centre (mm)")
    parser.add_argument("--out", type=Path, required=True, help="output directory (created)")
    parser.add_argument("--pixel", type=_positive_float, default=None,
                        help="raster pixel for unorganized clouds (mm; default: from the cloud's point spacing)")
    parser.add_argument("--units", choices=tuple(MM_PER_UNIT), default=None,
                        help="units of the cloud's coordinates (default: found from the plate's extent and --size)")
    parser.add_argument("--rings", type=_rings, default=RING_RADII_MM,
                        help=f"ring radii in mm (default {','.join(f'{r:g}' for r in RING_RADII_MM)})")
    defaults = BagLayout()
    parser.add_argument("--scan-topic", help=f"with --bag: the profiles' topic (default {defaults.scan_topic})")
    parser.add_argument("--base-frame", help=f"with --bag: the frame the sweeps are placed in "
                        f"(default {defaults.base_frame})")
    parser.add_argument("--sensor-frame", help=f"with --bag: the profiles' frame (default {defaults.sensor_frame})")
    args = parser.parse_args(argv)
    if args.cloud is not None and any(v is not None for v in (args.scan_topic, args.base_frame, args.sensor_frame)):
        parser.error("--scan-topic, --base-frame and --sensor-frame go with --bag")
    if args.bag is not None and args.units is not None:
        parser.error("--units goes with --cloud (a bag's clouds are in metres, REP 103)")
    try:
        if args.out.exists() and not args.out.is_dir():
            raise ValueError(f"{args.out}: exists and is not a directory")
        # Everything is prepared before the first file is written.
        if args.bag is not None:
            results = _bag_outputs(args)
            overview = {"bag": str(args.bag), "sweeps": {name: {"accepted": len(result[2].centres),
                                                                "rejected": int(result[2].rejected)}
                                                         for name, result in results.items()}}
        else:
            xyz, intensity = load_cloud(args.cloud)
            units = cloud_units(plate_extent(xyz), args.units, args.grid, args.size, max(args.rings))
            results = {"": _outputs(xyz * MM_PER_UNIT[units], intensity, args, str(args.cloud), units)}
    except ValueError as error:
        print(f"gls-measure: {error}", file=sys.stderr)
        return 2
    try:
        args.out.mkdir(parents=True, exist_ok=True)
        for folder, (texts, picture, _, _) in results.items():
            (args.out / folder).mkdir(exist_ok=True)
            atomic_write_bytes(args.out / folder / "detections.png", picture)
            for name, text in texts.items():
                atomic_write_text(args.out / folder / name, text)
        if args.bag is not None:
            atomic_write_text(args.out / "sweeps.json", json.dumps(overview, indent=2) + "\n")
    except OSError as error:
        print(f"gls-measure: cannot write to {args.out}: {error}", file=sys.stderr)
        return 2
    for folder, (_, _, measurement, seconds) in results.items():
        found = len(measurement.centres)
        where = f"{folder}: " if folder else ""
        if measurement.extra:
            print(f"gls-measure: warning: {where}{found} fiducials accepted, more than the {args.grid**2} of a "
                  f"{args.grid}x{args.grid} grid: check --grid", file=sys.stderr)
        print(f"{where}{found} of {args.grid**2} fiducials accepted, {measurement.rejected} candidate(s) rejected "
              f"in {seconds:.2f} s; written to {args.out / folder}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
