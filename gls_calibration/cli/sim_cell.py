"""gls-sim-cell: the headless simulated cell, every node in one process; calls ``calibrate``.

The cell is split as a real one is (:mod:`gls_calibration.cli.sim_streaming`): a simulated robot
that runs commanded lines and reports the flange on ``/tf``, a line scanner that streams profiles,
and ``stream_acquisition``, which places them through TF. ``--sweep-contract`` runs the package's
own sweep contract instead (``sim_scanner`` + ``scan_acquisition``: StartSweep, ``scan/pose``,
SweepDone), the only cell that can place profiles by time (``--placement time``).
With ``--serve`` it only starts the nodes and serves until interrupted, so that external clients
(``gls-calibrate``, ``gls-correct``, other machines on the same ROS_DOMAIN_ID) drive the cell.
``--measurement ideal|careful|paper_like|custom`` picks the simulated measurement chain (default:
the sim configuration's ``measurement.preset``, ``paper_like`` in the package's file); its name goes
into summary.json (``measurement_preset``) and the report. ``--reference-plate`` runs the simulated
reference-plate check instead of a calibration (no ROS) and writes ``DIR/summary.json``.
``--record BAG`` runs one calibration in-process on the direct cell and records it as a rosbag2 bag
(:mod:`gls_calibration.cli.sim_record`).
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import json
import math
import os
from pathlib import Path
import shutil
import sys
import time
from typing import Optional

import rclpy
import yaml
from rclpy.exceptions import ParameterException
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

from gls_calibration.calibration.procedure import ITERATIONS_LIMIT
from gls_calibration.calibration.stated_accuracy import load_chain_check, save_chain_check
from gls_calibration.cli import timeout_seconds
from gls_calibration.common.config_files import config_path, read_config_file
from gls_calibration.common.files import atomic_write_text
from gls_calibration.common.time_budget import ValidationCpuMark, unowned_threads_cpu_s
from gls_calibration.nodes.calibration_manager import CalibrationManager
from gls_calibration.nodes.correction import CorrectionNode
from gls_calibration.nodes.fiducial_measurement import FiducialMeasurementNode
from gls_calibration.nodes.plate_pose import PlatePoseNode
from gls_calibration.nodes.rbf_trainer import RbfTrainerNode
from gls_calibration.nodes.scan_acquisition import ScanAcquisitionNode
from gls_calibration.nodes.sim_galvo import SimGalvoNode
from gls_calibration.nodes.sim_scanner import SimScannerNode
from gls_calibration.registration.sweep_plan import parse_plan
from gls_calibration.report.files import write_summary_json
from gls_calibration.ros.dds import use_fast_liveliness
from gls_calibration.ros.manager_parameters import MANAGER_PARAMETERS, value_problem
from gls_calibration.ros.parameter_rules import unapplied_rule_problem
from gls_calibration.ros.runtime import NodeThreads, StopSignals, discard, exit_now_if_stuck
from gls_calibration.simulation.measurement import PRESETS
from gls_calibration.simulation.world import load_sim_config
from gls_calibration.cli.client import (ProgressBar, call_and_wait, ros_rules, split_ros_arguments,
                                        summary_table)
from gls_calibration_msgs.msg import CalibrationProgress
from gls_calibration_msgs.srv import Calibrate

# the CPU of threads no node owns, in the time budget's CPU by node (counted with the pipeline)
LIBRARY_THREADS = "library threads"
# the cell of --sweep-contract (the split cell's nodes: sim_streaming.streaming_nodes)
NODE_TYPES = (SimGalvoNode, SimScannerNode, ScanAcquisitionNode, PlatePoseNode, FiducialMeasurementNode,
              RbfTrainerNode, CorrectionNode, CalibrationManager)

MANAGER_NODE = "calibration_manager"
SEED_MAX = 2 ** 31 - 1    # the nodes declare ``seed`` as an integer parameter in [0, 2^31 - 1]
GRID_MAX = 101            # the manager's range of ``grid.per_side`` (3 to 101)


def max_iterations() -> int:
    """Return the most iterations the cell's manager accepts (``max_iterations`` of gls.yaml).

    Most iterations the cell's manager accepts: ``max_iterations`` of config/gls.yaml, the file it
    is given (``procedure.ProcedureSettings``' default when the file does not say).
    """
    from gls_calibration.calibration.procedure import ProcedureSettings

    def parse(document) -> object:
        try:
            return document["/**"]["ros__parameters"].get("max_iterations", ProcedureSettings.max_iterations)
        except (KeyError, TypeError, AttributeError):
            return None
    try:
        value = read_config_file(config_path("gls.yaml"), "parameter file", parse)
    except ValueError:
        value = None
    return value if isinstance(value, int) and not isinstance(value, bool) and value >= 1 \
        else ProcedureSettings.max_iterations


def manager_parameter_override(ros_arguments: list[str], namespace: str, name: str) -> Optional[str]:
    """Return the ``-p`` rule of ``ros_arguments`` that sets the manager's parameter ``name``.

    The ``-p``/``--param`` rule of ``ros_arguments`` that sets the cell manager's parameter ``name``
    (None when none does), as rcl picks it: the last ``calibration_manager:name:=V``, which beats any
    ``name:=V`` but reaches only a manager in the root namespace (rcl matches the node's full name), else
    the last ``name:=V``. ``namespace``: the cell's, unless a ``-r __ns:=...`` rule moves the nodes.
    """
    for rule in ros_rules(ros_arguments, "-r", "--remap"):
        target, _, value = rule.partition(":=")
        if target in ("__ns", f"{MANAGER_NODE}:__ns"):
            namespace = value
    everyone = own = None
    for rule in ros_rules(ros_arguments, "-p", "--param"):
        target = rule.partition(":=")[0]
        if target == name:
            everyone = rule
        elif target == f"{MANAGER_NODE}:{name}" and not namespace.strip("/"):
            own = rule
    return own or everyone


def iterations_limit(override: Optional[str]) -> int:
    """Return the manager's ``max_iterations`` given by the ``-p`` rule ``override``.

    Without a rule, config/gls.yaml's; ValueError naming the rule when the manager would not take
    its value.
    """
    if override is None:
        return max_iterations()
    text = override.partition(":=")[2]
    try:
        value = yaml.safe_load(text)    # how rcl reads a -p value
    except yaml.YAMLError:
        value = None
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= ITERATIONS_LIMIT:
        raise ValueError(f"--ros-args -p {override}: the manager's max_iterations must be an integer between 1 and "
                         f"{ITERATIONS_LIMIT}, got {text!r}")
    return value


def output_folder_problem(folder: Path) -> str:
    """Say why ``folder`` cannot be the cell's output folder (empty when it can).

    It must be a folder or not exist yet, below an existing folder (nothing is created here).
    """
    if folder.exists() or folder.is_symlink():
        return "" if folder.is_dir() else f"--out {folder} exists and is not a folder"
    for parent in folder.absolute().parents:
        if parent.exists():
            return "" if parent.is_dir() else f"--out {folder}: {parent} is not a folder"
    return ""


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """Parse the command line of gls-sim-cell.

    Command line of gls-sim-cell; ROS arguments after ``--ros-args`` go to every node (after the
    cell's own, so that they win).
    """
    own_arguments, user_ros_arguments = split_ros_arguments(argv)
    parser = argparse.ArgumentParser(prog="gls-sim-cell", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("reports/sim-cell"),
                        help="folder for the report, summary.json and the calibration store (OUT/calibrations; "
                             "a one-shot run is a new cell and starts that store afresh)")
    parser.add_argument("--seed", type=int, default=1,
                        help=f"seed of the simulated cell's random draws (0 to {SEED_MAX})")
    parser.add_argument("--grid", type=int, default=19, help=f"fiducials per side of the grid (3 to {GRID_MAX})")
    parser.add_argument("--iterations", type=int, default=1,
                        help=f"calibration iterations, each on a fresh plate (1 to {max_iterations()}, the "
                             "manager's max_iterations in config/gls.yaml, or N when '--ros-args -p "
                             "max_iterations:=N' sets it)")
    parser.add_argument("--sim-config", type=Path, default=None,
                        help="YAML parameter file of the simulated head's defects and noise "
                             "(default: the package's config/sim.yaml)")
    parser.add_argument("--no-validate", action="store_true", help="skip the validation grid")
    parser.add_argument("--force", action="store_true", help="train even when within tolerance")
    parser.add_argument("--physics-first", action="store_true",
                        help="fit the named physical effects first and the RBF on what they leave")
    parser.add_argument("--serve", action="store_true",
                        help="start every node and serve until interrupted, without calibrating")
    parser.add_argument("--timeout", type=timeout_seconds, default=600.0,
                        help="give up on calibrate after this (s)")
    parser.add_argument("--verbose", action="store_true", help="show the nodes' info logs")
    parser.add_argument("--measurement", choices=None, default=None, metavar="|".join(PRESETS),
                        help="measurement-chain preset of the simulated robot, scanner, marks and plate "
                             "(default: the sim configuration's measurement.preset, paper_like)")
    parser.add_argument("--sweep-plan", default=None, metavar="PLAN",
                        help="passes over the marked plate, e.g. 0+ (one forward sweep) or 0+,0-,90+,90- "
                             "(reversed and sensor turned: scanner-frame errors separated); default: config/gls.yaml")
    parser.add_argument("--placement", choices=("pose", "time"), default="pose",
                        help="place profiles by the robot's reported pose (default) or by time at the nominal "
                             "speed (a driver without a pose stream; with --sweep-contract only)")
    parser.add_argument("--reference-plate", action="store_true",
                        help="run the simulated reference-plate check (no calibration) and write DIR/summary.json "
                             "and DIR/reference_check.yaml")
    checks = parser.add_mutually_exclusive_group()
    checks.add_argument("--reference-check", type=Path, default=None, metavar="FILE",
                        help="the reference check of the chain the calibration states its accuracy from "
                             "(default for a one-shot run: measured first with the simulated reference plate, "
                             "written to DIR/reference_check.yaml; --serve uses one only when given)")
    checks.add_argument("--no-reference-check", action="store_true",
                        help="state no accuracy: the measured figures are self-consistency only")
    parser.add_argument("--chain-map", action="store_true",
                        help="measure the chain map of the calibration's lines first (the robot's repeating "
                             "error, with the simulated certified plate; DIR/chain_map.yaml), remove it from "
                             "every sweep of the marked plate, and measure the reference check with it")
    parser.add_argument("--record", type=Path, default=None, metavar="DIR",
                        help="run the calibration in-process on the direct simulated cell (no ROS graph) and "
                             "record every sweep (profiles, /tf, /tf_static, motion stamps) as a rosbag2 bag "
                             "in DIR (a new folder); replay with gls-measure --bag DIR")
    parser.add_argument("--record-storage", choices=("sqlite3", "mcap"), default="sqlite3",
                        help="storage of the recorded bag (default sqlite3)")
    cells = parser.add_mutually_exclusive_group()
    cells.add_argument("--sweep-contract", action="store_true",
                       help="the cell on the package's own sweep contract (sim_scanner and scan_acquisition: "
                            "StartSweep, scan/pose, SweepDone) instead of the split cell (simulated robot with TF "
                            "and the motion contract, streaming line scanner, stream_acquisition)")
    cells.add_argument("--streaming", action="store_true",
                       help="the split cell, which is the default (kept so that older command lines run)")
    parser.add_argument("--namespace", default=None,
                        help="namespace of the cell's nodes (default: 'gls' with --serve; otherwise a private "
                             "one, so that concurrent one-shot cells on the same ROS domain never meet)")
    args = parser.parse_args(own_arguments)
    args.user_ros_arguments = user_ros_arguments if own_arguments != user_ros_arguments else []
    if not 3 <= args.grid <= GRID_MAX:
        parser.error(f"--grid must be between 3 and {GRID_MAX}, got {args.grid}")
    # the manager refuses more iterations than its max_iterations, which a -p rule may set
    override = manager_parameter_override(user_ros_arguments, cell_namespace(args), "max_iterations")
    try:
        most_iterations = iterations_limit(override)
    except ValueError as error:
        parser.error(str(error))
    for parameter in MANAGER_PARAMETERS:   # rcl would keep the file's value of a rule of another type, silently
        rule = manager_parameter_override(user_ros_arguments, cell_namespace(args), parameter.name)
        if rule is not None:
            text = rule.partition(":=")[2]
            try:
                value = yaml.safe_load(text)   # how rcl reads a -p value
            except yaml.YAMLError:
                value = text
            problem = value_problem(parameter, value)
            if problem:
                parser.error(f"--ros-args -p {rule}: the manager's {problem}")
    if not 1 <= args.iterations <= most_iterations:
        origin = f", set by -p {override}" if override else ""
        parser.error(f"--iterations must be between 1 and {most_iterations} (the manager's max_iterations{origin}), "
                     f"got {args.iterations}")
    if not 0 <= args.seed <= SEED_MAX:
        parser.error(f"--seed must be between 0 and {SEED_MAX}, got {args.seed}")
    problem = output_folder_problem(args.out)
    if problem:
        parser.error(problem)
    if args.sim_config is not None and not args.sim_config.is_file():
        parser.error(f"--sim-config {args.sim_config}: no such file")
    if args.sweep_plan is not None:
        try:
            parse_plan(args.sweep_plan)
        except ValueError as error:
            parser.error(f"--sweep-plan: {error}")
    if args.chain_map and (args.record is not None or args.reference_plate or args.placement != "pose"):
        parser.error("--chain-map maps the reported pose along the ROS cell's lines: not with --record, "
                     "--reference-plate or --placement time")
    if args.record is not None:
        if args.serve or args.reference_plate:
            parser.error("--record runs one calibration: not with --serve or --reference-plate")
        if args.placement != "pose":
            parser.error("--record places profiles by the robot's pose (/tf): not with --placement time")
        if args.record.exists() or args.record.is_symlink():
            parser.error(f"--record {args.record}: exists already; a bag is written only into a new folder")
        if not args.record.parent.is_dir():
            parser.error(f"--record {args.record}: no such folder {args.record.parent}")
    if args.placement != "pose" and not args.sweep_contract and args.record is None and not args.reference_plate:
        parser.error("--placement time needs --sweep-contract: the split cell places every profile through TF")
    if (args.sweep_contract or args.streaming) and (args.record is not None or args.reference_plate):
        parser.error("--sweep-contract and --streaming pick the ROS cell's scanner: not with --record or "
                     "--reference-plate, which run no ROS cell")
    if args.measurement is not None and args.measurement not in PRESETS:
        parser.error(f"--measurement: unknown measurement preset {args.measurement!r}; known: {', '.join(PRESETS)}")
    try:
        # every node reads the same file: refuse a bad one before anything starts or is written
        # The run's --seed is the cell's seed (every node gets it as `seed`): the simulated robot's
        # repeating error field comes from it, so the reference check must be drawn with it too.
        args.sim = replace(load_sim_config(args.sim_config or config_path("sim.yaml"), args.measurement),
                           seed=args.seed)
        args.reference_plan = reference_plan(args)
        args.chain_map_file = None    # measured once the cell runs (--chain-map)
        if args.reference_check is not None:
            load_chain_check(args.reference_check)
    except ValueError as error:
        parser.error(str(error))
    return args


def cell_namespace(args: argparse.Namespace) -> str:
    """Return the namespace the cell's nodes get (a user's ``-r __ns:=...`` aside)."""
    return args.namespace or ("gls" if args.serve else f"gls_sim_{os.getpid()}")


def reference_plan(args: argparse.Namespace):
    """Return the sweep plan the calibration of this command line would run.

    The plan the calibration of this command line would run: config/gls.yaml's, with the
    ``--sweep-plan`` and ``--placement`` the cell's manager is given (see ``ros_arguments``).
    """
    from gls_calibration.simulation.reference_plate import calibration_plan

    plan = replace(calibration_plan(config_path("gls.yaml")), placed_by_pose=args.placement == "pose")
    return plan if args.sweep_plan is None else replace(plan, passes=parse_plan(args.sweep_plan))


def private_stream_remaps(args: argparse.Namespace) -> list[str]:
    """Return ``-r`` rules that move a one-shot split cell's absolute topics into its namespace.

    ``-r`` rules that move the split cell's absolute topics (``/tf``, ``/tf_static``, the motion
    contract, the profiles) into a one-shot cell's private namespace: its robot and scanner must not
    meet another cell's stream acquisition on the same ROS domain (seen: two runs at once, lines
    refused and profiles of the other cell's motions). None for a served cell or a ``--namespace``
    the user chose (absolute names, as drivers use them) and for the sweep contract (no such topics).
    """
    if args.serve or args.sweep_contract or args.namespace is not None:
        return []
    from gls_calibration.ros.stream_topics import LAYOUT, LINE_TOPIC

    topics = (LAYOUT.tf_topic, LAYOUT.tf_static_topic, LAYOUT.motion_start_topic, LAYOUT.motion_end_topic,
              LAYOUT.scan_topic, LINE_TOPIC)
    rules = []      # within the cell's --ros-args section (ros_arguments leaves it open)
    for topic in topics:
        rules += ["-r", f"{topic}:=/{cell_namespace(args)}{topic}"]
    return rules


def ros_arguments(args: argparse.Namespace, calibration_dir: Path, report_dir: Path) -> list[str]:
    """Parameter files and overrides shared by every node of the cell."""
    sim_config = args.sim_config or config_path("sim.yaml")
    overrides = {
        "seed": args.seed,
        "grid.per_side": args.grid,
        "calibration_dir": str(calibration_dir),
        "report_dir": str(report_dir),
        "report_per_run": False,
        "plate_exchange_service": "sim/exchange_plate",
        "ground_truth_service": "sim/marked_paths",
        "physics_first": args.physics_first,
        "sim_config": str(sim_config),
        "measurement_preset": args.measurement or "",
        "report.simulated_chain": args.sim.measurement_preset,   # what the manager's report names
        "use_pose_stream": args.placement == "pose",
        "sweep.placed_by_pose": args.placement == "pose",
    }
    if args.sweep_plan is not None:
        overrides["sweep.plan"] = args.sweep_plan
    if not args.sweep_contract:
        overrides["marks_service"] = "sim/marked_paths"
    if args.reference_check is not None:
        overrides["reference_check_file"] = str(args.reference_check.resolve())
    if args.chain_map_file is not None:
        overrides["chain_map_file"] = str(args.chain_map_file.resolve())
    ros_args = ["--ros-args", "--log-level", "info" if args.verbose else "warn"]
    for path in (config_path("head.yaml"), config_path("gls.yaml"), sim_config):
        ros_args += ["--params-file", str(path)]
    for name, value in overrides.items():
        ros_args += ["-p", f"{name}:={json.dumps(value) if isinstance(value, str) else value}"]
    return ros_args


def main(argv: list[str] | None = None) -> int:
    """Run the simulated cell; exit 0 when the calibration succeeded."""
    args = parse_args(argv)   # every argument is checked before anything starts or is created
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        print(f"gls-sim-cell: cannot create --out {args.out}: {error.strerror or error}", file=sys.stderr)
        return 2
    if args.reference_plate:
        return run_reference_plate(args)
    if args.record is not None:
        from gls_calibration.cli.sim_record import run_recording

        shutil.rmtree(args.out / "calibrations", ignore_errors=True)    # a one-shot run is a new cell
        return run_recording(args)
    try:
        args.chain_map_file = measure_chain_map_file(args) if args.chain_map else None
    except ValueError as error:
        print(f"gls-sim-cell: the chain map could not be measured: {error}", file=sys.stderr)
        return 1
    if args.reference_check is None and not (args.serve or args.no_reference_check):
        args.reference_check = measure_reference_check(args)
    # The store lives beside the report, so the summary names the calibration file where it stays.
    # Every one-shot run is a new simulated cell and starts with an empty store; --serve keeps the
    # store so that successive external calibrations compose.
    store = args.out / "calibrations"
    if not args.serve:
        shutil.rmtree(store, ignore_errors=True)
    use_fast_liveliness()
    # SIGINT/SIGTERM handled once (runtime.StopSignals); rclpy's own handlers stay off.
    stop = StopSignals()
    context = rclpy.Context()
    # "--" ends the cell's ROS arguments; the user's command line follows with its own --ros-args.
    user = ["--", *args.user_ros_arguments] if args.user_ros_arguments else []
    cell_arguments = ros_arguments(args, store, args.out) + private_stream_remaps(args) + user
    rclpy.init(args=cell_arguments, context=context, signal_handler_options=SignalHandlerOptions.NO)
    namespace = cell_namespace(args)
    nodes: list = []
    threads: Optional[NodeThreads] = None
    status = 1
    try:
        try:
            if not args.sweep_contract:
                from gls_calibration.cli.sim_streaming import streaming_nodes

                built = streaming_nodes(context, namespace)
            else:
                built = (node_type(context=context, namespace=namespace) for node_type in NODE_TYPES)
            for node in built:
                nodes.append(node)
                # rcl drops some -p rules without a word (another type than the file's, []): refuse them
                problem = unapplied_rule_problem(node, cell_arguments)
                if problem:
                    raise ValueError(f"{node.get_name()}: {problem}")
        except (ValueError, TypeError, ParameterException) as error:
            # a parameter a node refuses at start (e.g. grid.size_mm:=abc): said, nothing runs
            print(f"gls-sim-cell: {error}", file=sys.stderr)
            status = 2
            return status
        threads = NodeThreads(nodes)
        if args.serve:
            names = ", ".join(node.get_fully_qualified_name() for node in nodes)
            print(f"serving the simulated cell ({names}); Ctrl-C to stop", flush=True)
            while not stop.requested.wait(0.5):
                pass
            status = stop.exit_status
            return status
        if stop.requested.is_set():      # a signal while the nodes were built
            status = stop.exit_status
            return status
        stop.interrupting = True         # Ctrl-C now ends the wait for calibrate's answer
        status = run_calibration(args, nodes[-1], threads)
        return status
    except KeyboardInterrupt:
        status = stop.exit_status
        return status
    finally:
        stop.stopping()
        # Order (runtime.NodeThreads.stop): no new work, runs canceled, owned threads joined, executors
        # shut down, nodes destroyed; then the context.
        if threads is not None:
            left = threads.stop()
        else:
            left = []
            for node in nodes:
                discard(node)
        context.try_shutdown()
        stop.restore()
        exit_now_if_stuck(left, status)


def run_calibration(args: argparse.Namespace, manager: CalibrationManager, threads: NodeThreads) -> int:
    """Call ``calibrate`` from a client node of the cell, with a progress bar.

    Print the summary and the time budget.
    """
    client_node = rclpy.create_node("sim_cell_client", namespace=manager.get_namespace(), context=manager.context)
    bar = ProgressBar(sys.stderr)
    library_start_s = unowned_threads_cpu_s(threads.threads)

    def cpu_s() -> dict[str, float]:
        # threads no node owns (OpenCV's pool, the nodes' workers, DDS), from the request on: the pipeline's
        # (the simulation's share of DDS included, so the figure errs high rather than low)
        return {**threads.cpu_s(), LIBRARY_THREADS: unowned_threads_cpu_s(threads.threads) - library_start_s}
    validation_mark = ValidationCpuMark(cpu_s)

    def on_progress(message) -> None:
        validation_mark.observe(message.stage)
        bar.update(message)
    client_node.create_subscription(CalibrationProgress, "calibration/progress", on_progress, 10)
    client = client_node.create_client(Calibrate, "calibrate")
    executor = SingleThreadedExecutor(context=manager.context)
    executor.add_node(client_node)
    request = Calibrate.Request(iterations=args.iterations, validate=not args.no_validate, force=args.force)
    try:
        response = call_and_wait(executor, client, request, args.timeout)
    finally:
        executor.shutdown()
        client_node.destroy_node()
    bar.finish()
    if response is None:
        print(f"calibrate did not answer within {args.timeout:g} s", file=sys.stderr)
        return 1
    print(summary_table(response))
    if response.report_dir:
        truth = json.loads((Path(response.report_dir) / "summary.json").read_text())
        if truth.get("true_post_rms_mm") is not None:
            print(f"true error after (simulation ground truth): RMS {truth['true_post_rms_mm']:.4f} mm, "
                  f"max {truth['true_post_max_mm']:.4f} mm")
        if truth.get("certificate_u95_median_mm") is not None:
            covered = truth.get("certificate_coverage")
            print(f"certificate U (95 % radius): median {truth['certificate_u95_median_mm']:.4f} mm, largest "
                  f"{truth['certificate_u95_full_mm']:.4f} mm"
                  + (f"; TRUE landings within U {covered:.1%}" if covered is not None else ""))
        at_validation = validation_mark.at_validation_s if request.validate else None
        print(write_time_budget(Path(response.report_dir), truth, cpu_s(), at_validation))
    if not response.success:
        print(f"calibration failed: {response.message}", file=sys.stderr)
        return 1
    print(f"report: {Path(response.report_dir) / 'report.md'}")
    return 0


def write_time_budget(report_dir: Path, summary: dict, cpu_by_node: dict[str, float],
                      cpu_at_validation: Optional[dict[str, float]] = None) -> str:
    """Write ``report_dir/time_budget.json`` and return the table printed from it.

    ``report_dir/time_budget.json`` (the run's cell time, wall time per stage, CPU per node; see
    ``time_budget``) and the table printed from it; ``summary`` (the run's ``summary.json`` as read)
    is written back with ``compute_cpu_s``. The simulated nodes' CPU (``sim_*``) is the
    simulation's, not the pipeline's; that of threads no node owns (``LIBRARY_THREADS``) is counted
    with the pipeline.
    ``cpu_at_validation`` (CPU per node as the validation plate began, ``ValidationCpuMark``) splits
    ``compute_cpu_s`` into ``compute_cpu_s_before_validation`` (the training plates and their
    training) and ``compute_cpu_s_from_validation`` (the validation plate, the report, the
    activation); both null without it.
    """
    def pipeline_of(cpu: dict[str, float]) -> dict[str, float]:
        return {name: value for name, value in cpu.items() if not name.startswith("sim_")}
    pipeline = pipeline_of(cpu_by_node)
    simulation = {name: cpu for name, cpu in cpu_by_node.items() if name not in pipeline}
    total_s = sum(pipeline.values())
    before_s = sum(pipeline_of(cpu_at_validation).values()) if cpu_at_validation else None
    if before_s is not None and not math.isfinite(before_s):
        before_s = None     # a thread that ended has no clock: no split rather than a wrong one
    budget = {"cell_time_s": summary.get("cell_time_s"), "stage_wall_s": summary.get("stage_wall_s", {}),
              "last_sweep_to_result_s": summary.get("last_sweep_to_result_s"),
              "last_profile_to_activation_s": summary.get("last_profile_to_activation_s"),
              "cpu_s_by_node": cpu_by_node, "compute_cpu_s": total_s,
              "compute_cpu_s_before_validation": before_s,
              "compute_cpu_s_from_validation": None if before_s is None else total_s - before_s,
              "simulation_cpu_s": sum(simulation.values()), "process_cpu_s": time.process_time()}
    atomic_write_text(report_dir / "time_budget.json", json.dumps(budget, indent=2) + "\n")
    # the manager cannot see other nodes' CPU; here they share this process, so the summary gets it
    write_summary_json(report_dir, {**summary, "compute_cpu_s": total_s})

    def seconds(value) -> str:
        return "n/a" if value is None or not math.isfinite(value) else f"{value:.1f} s"

    stages = ", ".join(f"{stage} {seconds(value)}" for stage, value in budget["stage_wall_s"].items())
    nodes = ", ".join(f"{name} {seconds(value)}" for name, value in sorted(pipeline.items(), key=lambda i: -i[1]))
    split = ("" if before_s is None else f" (training plate and training {seconds(before_s)}, validation plate, "
             f"report and activation {seconds(budget['compute_cpu_s_from_validation'])})")
    return "\n".join([
        f"time budget: cell time {seconds(budget['cell_time_s'])} (simulated robot, sweeps, marking)",
        f"  wall by stage: {stages}",
        f"  last sweep to result: {seconds(budget['last_sweep_to_result_s'])}, to the activation "
        f"{seconds(budget['last_profile_to_activation_s'])}",
        f"  CPU of the pipeline {seconds(budget['compute_cpu_s'])}{split}: {nodes}",
        f"  CPU of the simulation {seconds(budget['simulation_cpu_s'])}; whole process "
        f"{seconds(budget['process_cpu_s'])} (imports, the reference check and the process's other threads included)"])


def measure_chain_map_file(args: argparse.Namespace) -> Path:
    """Measure the chain map of the calibration's lines on the simulated robot.

    The certified plate is swept along them, as a real cell would; the map is written to
    DIR/chain_map.yaml.
    """
    from gls_calibration.registration.chain_map import save_chain_map
    from gls_calibration.simulation.reference_plate import FIELD_PLATE, measure_chain_map

    print(f"chain map of the lines {args.reference_plan.label} (certified plate {FIELD_PLATE.label})",
          file=sys.stderr, flush=True)
    path = args.out / "chain_map.yaml"
    save_chain_map(path, measure_chain_map(args.sim, args.reference_plan, seed=args.seed))
    return path


def measure_reference_check(args: argparse.Namespace) -> Path:
    """Measure the simulated reference plate with the calibration's plan before the calibration.

    It is measured on the same robot (as a real cell checks its chain with a certified plate), with
    the run's chain map applied when it has one; the check is written to DIR/reference_check.yaml.
    """
    from gls_calibration.registration.chain_map import load_chain_map
    from gls_calibration.simulation.reference_plate import FIELD_PLATE, chain_check, reference_plate_check

    chain_map = load_chain_map(args.chain_map_file) if args.chain_map_file else None
    print(f"reference check of the chain ({args.reference_plan.label}, placed by {args.reference_plan.placement}, "
          f"certified plate {FIELD_PLATE.label}{', chain map applied' if chain_map else ''})",
          file=sys.stderr, flush=True)
    # Same robot (its repeating field comes from the cell's seed); the check's sweeps and plate draw
    # their own per-sweep errors and texture (reference_plate.measure_plate's seeds).
    result = reference_plate_check(args.sim, args.reference_plan, seed=args.seed, design=FIELD_PLATE,
                                   chain_map=chain_map)
    path = args.out / "reference_check.yaml"
    save_chain_check(path, chain_check(result, args.reference_plan, args.sim, args.seed, FIELD_PLATE, chain_map))
    return path


def run_reference_plate(args: argparse.Namespace) -> int:
    """Run the simulated reference-plate check (no ROS): write ``summary.json`` and print the figures."""
    from gls_calibration.simulation.reference_plate import (PATTERN, PITCH_MM, POSITIONS_MM, RAW_PLAN,
                                                            chain_check, reference_plate_check)

    plan = args.reference_plan
    raw = reference_plate_check(args.sim, RAW_PLAN, seed=args.seed)
    planned = raw if plan == RAW_PLAN else reference_plate_check(args.sim, plan, seed=args.seed)
    summary = {
        "measurement_preset": args.sim.measurement_preset,
        "reference_plate": (f"double-ring fiducials r = 2.5 / 2.7 mm, {PATTERN[0]} x {PATTERN[1]} at {PITCH_MM:g} mm "
                            f"pitch, plate centre at {len(POSITIONS_MM)} positions {list(POSITIONS_MM)} mm"),
        "reference_plate_raw_sigma_mm": list(raw.sigma_mm),
        "reference_plate_raw_bias_mm": [list(b) for b in raw.bias_mm],
        "reference_plate_raw_plan": {"sweep_plan": RAW_PLAN.label, "placement": RAW_PLAN.placement,
                                     "plain_sweeps": RAW_PLAN.plain_sweeps},
        "reference_plate_sigma_mm": list(planned.sigma_mm),
        "reference_plate_bias_mm": [list(b) for b in planned.bias_mm],
        "reference_plate_plan": {"sweep_plan": plan.label, "placement": plan.placement,
                                 "plain_sweeps": plan.plain_sweeps,
                                 "combined_by": "procedure.combined_centres_gls (sweep_plan.combine_sweeps)"},
        "reference_plate_found": planned.found,
        "reference_plate_expected": planned.expected,
        "seed": args.seed,
    }
    atomic_write_text(args.out / "summary.json", json.dumps(summary, indent=2) + "\n")
    save_chain_check(args.out / "reference_check.yaml", chain_check(planned, plan, args.sim, args.seed))
    print(f"reference plate, preset {summary['measurement_preset']} (MEASURED against the known centres, k = 1): "
          f"raw sigma x {raw.sigma_mm[0]:.4f} mm, y {raw.sigma_mm[1]:.4f} mm (one sweep, placed by time); "
          f"calibration plan ({plan.label}, placed by {plan.placement}) x {planned.sigma_mm[0]:.4f} mm, "
          f"y {planned.sigma_mm[1]:.4f} mm; "
          f"{planned.found} of {planned.expected} centres")
    print(f"summary: {args.out / 'summary.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
