"""How often the simulated cell fails to stop cleanly: exit statuses of repeated runs.

Two modes, each under an optional parallel CPU load (``--load N`` busy processes):

* ``serve``: ``gls-sim-cell --serve --grid 3`` (one sweep per plate), one ``calibrate`` from this
  process, SIGINT ``--delay`` seconds after the answer; the documented status is 130.
* ``oneshot``: ``gls-sim-cell --grid G --seed S --out DIR`` to the end; the documented status is 0
  (or 1 for a calibration that failed).

Prints every run's status and the count of each, e.g.::

    python benchmarks/bench_shutdown.py serve --runs 20 --load 1
"""
from __future__ import annotations

import argparse
from collections import Counter
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# one sweep per plate; wide time limits (a loaded machine must not fail the calibration before the stop)
FAST = ["--ros-args", "-p", "sweep.plain_repeats:=1", "-p", "sweep.plan:=0+", "-p", "deadline_factor:=10.0"]
BUSY = "while True: pass"


def serve_once(directory: Path, delay_s: float, timeout_s: float) -> tuple[int | str, float]:
    """One served cell, one calibration, SIGINT ``delay_s`` after the answer: (status, stop time s)."""
    from gls_calibration.cli.client import call_and_wait, client_node
    from gls_calibration_msgs.srv import Calibrate

    log = open(directory / "cell.log", "w")
    cell = subprocess.Popen([sys.executable, "-m", "gls_calibration.cli.sim_cell", "--serve", "--grid", "3",
                             "--out", str(directory / "out"), *FAST], stdout=log, stderr=subprocess.STDOUT)
    try:
        with client_node("bench_shutdown", "gls") as (node, executor):
            client = node.create_client(Calibrate, "calibrate")
            client.wait_for_service(timeout_sec=120.0)     # a loaded machine starts the cell slowly
            answer = call_and_wait(executor, client, Calibrate.Request(validate=False, force=True), timeout_s)
        if answer is None or not answer.success:
            print(f"  calibration failed: {answer and answer.message}", file=sys.stderr)
        time.sleep(delay_s)
        cell.send_signal(signal.SIGINT)
        began = time.monotonic()
        try:
            return cell.wait(timeout=15.0), time.monotonic() - began
        except subprocess.TimeoutExpired:
            return "hang", time.monotonic() - began
    finally:
        if cell.poll() is None:
            cell.kill()
            cell.wait()
        log.close()


def oneshot_once(directory: Path, seed: int, grid: int, timeout_s: float) -> tuple[int | str, float]:
    """One ``gls-sim-cell`` run to its end: (status, run time s)."""
    began = time.monotonic()
    try:
        done = subprocess.run([sys.executable, "-m", "gls_calibration.cli.sim_cell", "--grid", str(grid),
                               "--seed", str(seed), "--out", str(directory / "out"), "--no-reference-check",
                               *FAST], capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return "hang", time.monotonic() - began
    if "terminate called" in done.stderr:
        print("  " + done.stderr.strip().splitlines()[-1], file=sys.stderr)
    return done.returncode, time.monotonic() - began


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", choices=("serve", "oneshot"))
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--load", type=int, default=1, help="busy processes running meanwhile")
    parser.add_argument("--delay", type=float, default=0.5, help="serve: SIGINT this long after the answer (s)")
    parser.add_argument("--grid", type=int, default=3)
    parser.add_argument("--seed", type=int, default=32)
    args = parser.parse_args()
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(101, 200)))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    load = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(args.load)]
    statuses = Counter()
    try:
        for run in range(args.runs):
            with tempfile.TemporaryDirectory() as folder:
                if args.mode == "serve":
                    status, seconds = serve_once(Path(folder), args.delay, 300.0)
                else:
                    status, seconds = oneshot_once(Path(folder), args.seed + run, args.grid, 600.0)
            statuses[status] += 1
            print(f"run {run + 1:2d}: status {status} ({seconds:.1f} s)", flush=True)
    finally:
        for process in load:
            process.kill()
            process.wait()
    print(f"{args.mode}, {args.runs} runs, load {args.load}: " +
          ", ".join(f"status {status}: {count}" for status, count in sorted(statuses.items(), key=str)))


if __name__ == "__main__":
    main()
