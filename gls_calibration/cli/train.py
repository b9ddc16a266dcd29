"""gls-train: a calibration file from measured fiducials, without a running cell.

Input: a CSV ``x_cmd,y_cmd,x_meas,y_meas`` (mm): targets commanded through the nominal model on the
plane z = 0 of the gls frame (or ``--plane-z``, or the mean of an optional ``z_cmd`` column, as the
main job's ``training.csv`` has it), and where they were measured, in any frame a rigid motion away
(the measurement is aligned onto the targets first, as the calibrate flow does).
The model is trained exactly as the calibrate flow trains it (:func:`gls_calibration.models.training.
train_correction`, grid search from ``config/gls.yaml``), at the measured points on ``Q - P``. The
calibrated region is the box of the commanded targets. Writes ``--out`` (the calibration YAML) and
``<out>.report.md`` beside it. Exit 0, or 2 with a message and nothing written on bad input.
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path
import sys
from typing import Any, Mapping, Optional

import numpy as np

from gls_calibration.calibration.record import TAPER_MM, calibration_record, region_around
from gls_calibration.calibration.record_file import dump_record
from gls_calibration.common.config_files import config_path, read_config_file
from gls_calibration.common.files import atomic_write_text, require_regular_output
from gls_calibration.correction.setpoints import check_calibration_plane
from gls_calibration.fiducials.targets import RING_RADII_MM
from gls_calibration.geometry.head_config import default_head_config_path, load_head_config
from gls_calibration.models.training import (GRID_SEARCH_PARAMETERS, TRAINER_PARAMETERS, TrainingOptions,
                                             train_correction, training_options_from)
from gls_calibration.registration.rigid import align_rigid_2d

COLUMNS = ("x_cmd", "y_cmd", "x_meas", "y_meas")


def read_measured(path: Path) -> tuple[np.ndarray, np.ndarray, Optional[float]]:
    """Read commanded (N, 2) and measured (N, 2) points and the mean ``z_cmd`` from the CSV.

    ``z_cmd`` is None without that column; ValueError naming the problem.
    """
    try:
        with path.open(newline="") as stream:
            reader = csv.DictReader(stream)
            header = reader.fieldnames or []
            missing = [name for name in COLUMNS if name not in header]
            if missing:
                raise ValueError(f"{path}: missing column(s) {', '.join(missing)} (header: {','.join(header)})")
            names = COLUMNS + (("z_cmd",) if "z_cmd" in header else ())
            values = np.array([[float(row[name]) for name in names] for row in reader]).reshape(-1, len(names))
    except (TypeError, ValueError) as error:
        if str(error).startswith(str(path)):
            raise
        raise ValueError(f"{path}: non-numeric value: {error}") from None
    if values.shape[0] < 10:
        raise ValueError(f"{path}: {values.shape[0]} row(s); at least 10 measured fiducials are needed")
    bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
    if bad.size:
        raise ValueError(f"{path}: {bad.size} row(s) with NaN or infinite values (first: data row {bad[0] + 1})")
    return values[:, :2], values[:, 2:4], float(np.mean(values[:, 4])) if values.shape[1] > 4 else None


TRAINER_NODE = "rbf_trainer"
TRAINER_PARAMETER_NAMES = tuple(spec.name for spec in TRAINER_PARAMETERS)   # what rbf_trainer declares
LAYOUT = (f"a ROS parameter file '/**:' or '{TRAINER_NODE}:' -> 'ros__parameters:' holding the trainer's "
          f"parameters ({', '.join(GRID_SEARCH_PARAMETERS)}), as config/gls.yaml")


def _flatten(parameters: Mapping, prefix: str = "") -> dict[str, Any]:
    """Dotted parameter names (how ROS reads nested blocks) -> values."""
    flat: dict[str, Any] = {}
    for key, value in parameters.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            flat.update(_flatten(value, name + "."))
        else:
            flat[name] = value
    return flat


def _package_parameter_names() -> set[str]:
    """Return every parameter name of the package's own parameter files.

    The files are gls.yaml, head.yaml and sim.yaml: what the cell's nodes read from the ``/**``
    block they share.
    """
    names: set[str] = set(TRAINER_PARAMETER_NAMES)
    for name in ("gls.yaml", "head.yaml", "sim.yaml"):
        document = read_config_file(config_path(name), "parameter file", lambda document: document)
        names |= set(_flatten(document["/**"]["ros__parameters"]))
    return names


def _known(name: str, known: set[str]) -> bool:
    # head.effects.<effect> is an open list of named effects (head_config checks the names)
    return name in known or name.startswith(("head.effects.", "effects."))


def trainer_parameters(document: Any) -> dict[str, Any]:
    """Return the rbf_trainer's parameters of a ROS parameter file.

    First the ``/**`` block every node reads, then the ``rbf_trainer`` block (which wins, as for the
    node; a namespaced ``/ns/rbf_trainer`` too). ValueError when neither holds a grid-search
    parameter or a block names a parameter nobody reads.
    """
    if not isinstance(document, Mapping):
        raise ValueError(f"expected {LAYOUT}; got a {type(document).__name__} (not a parameter file)")
    merged: dict[str, Any] = {}
    blocks = [key for key in document if str(key).rstrip("/").split("/")[-1] == TRAINER_NODE]
    for key in (["/**"] if "/**" in document else []) + blocks:
        block = document[key]
        parameters = block.get("ros__parameters") if isinstance(block, Mapping) else None
        if not isinstance(parameters, Mapping):
            raise ValueError(f"'{key}' must hold a mapping 'ros__parameters:'; expected {LAYOUT}")
        flat = _flatten(parameters)
        # the wildcard block is every node's; the trainer's own block holds its parameters and the head's
        known = _package_parameter_names() if key == "/**" else set(TRAINER_PARAMETER_NAMES)
        unknown = sorted(name for name in flat
                         if not (_known(name, known) or (key != "/**" and name.startswith("head."))))
        if unknown:
            raise ValueError(f"unknown parameter(s) {', '.join(map(repr, unknown))} under '{key}'; the trainer reads "
                             f"{', '.join(TRAINER_PARAMETER_NAMES)}")
        merged.update(flat)
    if not any(name in merged for name in GRID_SEARCH_PARAMETERS):
        raise ValueError(f"no trainer parameters found; expected {LAYOUT}")
    return merged


def training_options(config: Path) -> TrainingOptions:
    """Return the trainer's grid search from a parameter file (the keys the rbf_trainer node reads, with its ranges)."""
    def parse(document: Any) -> TrainingOptions:
        parameters = trainer_parameters(document)
        # the node's own table and checks: a value one refuses, the other refuses too
        return training_options_from({spec.name: spec.check(parameters[spec.name], "trainer parameter")
                                      for spec in TRAINER_PARAMETERS if spec.name in parameters})
    return read_config_file(config, "parameter file", parse)


def train_file(measured_csv: Path, head_file: Path, config: Path, physics_first: bool,
               plane_z_mm: Optional[float]):
    """(record, report text): the calibration the CSV gives (plane: ``plane_z_mm``, else the CSV's, else 0)."""
    commanded, measured, commanded_height = read_measured(measured_csv)
    if plane_z_mm is None:
        plane_z_mm = commanded_height if commanded_height is not None else 0.0
    geometry, _known = load_head_config(head_file)
    check_calibration_plane(geometry, plane_z_mm)      # before the training, not when the file is loaded
    aligned = align_rigid_2d(measured, commanded)[1]
    # Commanding Q through the nominal model landed at P: Q - P is the correction to add at P.
    corrections = commanded - aligned
    trained = train_correction(aligned, corrections, geometry, physics_first=physics_first,
                               options=training_options(config))
    region = region_around(commanded, RING_RADII_MM, plane_z_mm)   # the fiducials' rings, as the calibrate flow
    rms = float(np.sqrt(np.mean(np.sum(corrections ** 2, axis=1))))
    worst = float(np.max(np.linalg.norm(corrections, axis=1)))
    record = calibration_record(
        geometry, plate_pose={"normal": [0.0, 0.0, 1.0], "centre": [0.0, 0.0, plane_z_mm], "rotation": np.eye(3),
                              "flatness_rms_mm": 0.0},
        models=[trained.model], trained=[trained], region=region, targets_xy=commanded,
        measured_xyz=np.column_stack([aligned, np.full(len(commanded), plane_z_mm)]), deviations_xy=corrections,
        through_nominal_model=True,
        metrics={"training": {"count": len(commanded), "rms_abs_mm": rms, "max_abs_mm": worst}},
        source={"tool": "gls-train", "measured": str(measured_csv), "head": str(head_file),
                "trainer_config": str(config), "physics_first": physics_first})
    report = "\n".join([
        "# gls-train", "",
        f"- measured fiducials: {measured_csv} ({len(commanded)} points), head {head_file}, grid search {config}",
        f"- deviations Q - P after rigid alignment (MEASURED): RMS {rms:.4f} mm, max {worst:.4f} mm",
        f"- model: {trained.description or trained.method}",
        f"- calibrated region: x [{region.x_min:g}, {region.x_max:g}] mm, y [{region.y_min:g}, {region.y_max:g}] mm "
        f"on z = {plane_z_mm:g} mm, taper {TAPER_MM:g} mm", ""])
    return record, report


def main(argv: Optional[list[str]] = None) -> int:
    """Exit 0 on success, 2 on bad input or an unwritable output (nothing written)."""
    parser = argparse.ArgumentParser(prog="gls-train", description=__doc__.split("\n\n")[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--measured", type=Path, help="CSV x_cmd,y_cmd,x_meas,y_meas (mm)")
    source.add_argument("--bag", type=Path, help="rosbag2 recording of a calibration: the calibrate flow run "
                        "again from it (report in <out>.report/)")
    parser.add_argument("--out", type=Path, required=True, help="calibration file to write (YAML)")
    parser.add_argument("--physics-first", action="store_true", help="fit the named physical effects first")
    parser.add_argument("--head", type=Path, default=None, help="head file (default: config/head.yaml)")
    parser.add_argument("--config", type=Path, default=None, help="trainer grid search (default: config/gls.yaml)")
    parser.add_argument("--plane-z", type=float, default=None,
                        help="height the targets were commanded at (mm; default: mean z_cmd of the CSV, else 0)")
    bag = parser.add_argument_group("with --bag")
    bag.add_argument("--grid", type=int, default=None, help="fiducials per side (default: config/gls.yaml)")
    bag.add_argument("--grid-size", type=float, default=None, help="grid span in mm (default: config/gls.yaml)")
    bag.add_argument("--sweep-plan", default=None, help="passes over the marked plate (default: config/gls.yaml)")
    bag.add_argument("--plain-sweeps", type=int, default=None, help="plain sweeps per plate (default: config/gls.yaml)")
    bag.add_argument("--standstill-height", action=argparse.BooleanOptionalAction, default=None,
                     help="each plate's plain sweeps are followed by stand-still profiles at the marking pose "
                     "(default: config/gls.yaml)")
    bag.add_argument("--validate", action="store_true", help="the bag's last plate is the validation plate")
    bag.add_argument("--force", action="store_true", help="train even when within tolerance")
    bag.add_argument("--scan-topic", default=None, help="the profiles' topic")
    bag.add_argument("--base-frame", default=None, help="the robot base frame")
    bag.add_argument("--sensor-frame", default=None, help="the profiles' frame")
    args = parser.parse_args(argv)
    bag_only = ("grid", "grid_size", "sweep_plan", "plain_sweeps", "standstill_height", "validate", "force",
                "scan_topic", "base_frame", "sensor_frame")
    if args.bag is None and any(getattr(args, name) not in (None, False) for name in bag_only):
        parser.error("--grid, --grid-size, --sweep-plan, --plain-sweeps, --standstill-height, --validate, --force and "
                     "the topic and frame options go with --bag")
    if args.bag is not None:
        from gls_calibration.cli.train_bag import recording_settings, train_from_bag

        if args.plane_z is not None:
            parser.error("--plane-z goes with --measured (with --bag the plate pose gives the plane)")
        try:
            settings = recording_settings(args.grid, args.grid_size, args.sweep_plan, args.plain_sweeps,
                                          args.standstill_height)
            args.training = training_options(args.config or config_path("gls.yaml"))
        except ValueError as error:
            print(f"gls-train: {error}", file=sys.stderr)
            return 2
        args.head = args.head or default_head_config_path()
        return train_from_bag(args, settings)
    try:
        if args.plane_z is not None and not np.isfinite(args.plane_z):
            raise ValueError(f"--plane-z must be finite, got {args.plane_z}")
        # both outputs checked before the training: a device, FIFO, folder or symlink is refused
        require_regular_output(args.out)
        report_path = args.out.with_name(args.out.name + ".report.md")
        require_regular_output(report_path)
        record, report = train_file(args.measured, args.head or default_head_config_path(),
                                    args.config or config_path("gls.yaml"), args.physics_first, args.plane_z)
        text = dump_record(record)
    except (OSError, ValueError) as error:
        print(error, file=sys.stderr)
        return 2
    report_existed = report_path.exists()
    try:   # the report first: a failed calibration write then leaves no new report behind
        atomic_write_text(report_path, report)
        atomic_write_text(args.out, text)
    except (OSError, ValueError) as error:   # ValueError: an output replaced by a non-regular file meanwhile
        if not report_existed:
            report_path.unlink(missing_ok=True)
        print(f"cannot write {args.out}: {getattr(error, 'strerror', None) or error}", file=sys.stderr)
        return 2
    print(f"calibration written to {args.out} ({record['hyper_parameters']['trained_models'][0]['method']}); "
          f"report {report_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
